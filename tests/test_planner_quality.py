"""The planner benchmark's restart test (benchmarks/planner_quality.py), on empty roads and in traffic."""

from __future__ import annotations

import pytest
from helpers import always_brake, load_benchmark

from gccp_envs.config import IntersectionConfig
from gccp_envs.scripted import SearchPlanner


@pytest.fixture(scope="module")
def planner_quality():
    return load_benchmark("planner_quality")


def test_a_planner_that_never_drives_off_stalls_after_every_stop_in_traffic(planner_quality):
    result = planner_quality.restarting(always_brake, episodes=1, seed=0, traffic=True)
    assert result["stops"] >= 1
    assert result["restart_rate"] == 0.0
    assert result["completion_after_stop"] == 0.0
    assert result["timeout_after_stop"] + result["crash_after_stop"] == pytest.approx(1.0)
    assert result["timeout_after_stop"] > 0.0


def test_the_search_planner_drives_off_after_its_stops_on_an_empty_road(planner_quality):
    result = planner_quality.restarting(SearchPlanner(IntersectionConfig()), episodes=1, seed=0)
    assert result["stops"] >= 1
    assert result["restart_rate"] == 1.0
    assert result["timeout_after_stop"] == 0.0
    assert result["crash_after_stop"] == 0.0


def test_set_runs_the_benchmark_in_that_world(planner_quality, monkeypatch):
    """--set KEY=VALUE reaches every env the benchmark builds; a bad key is one usage error (exit 2)."""
    from gccp_envs.option_env import GCCPDeciderEnv

    seen = []
    real_init = GCCPDeciderEnv.__init__

    def spy(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        seen.append(self.config.rear_axle_offset)

    monkeypatch.setattr(GCCPDeciderEnv, "__init__", spy)
    planner_quality.restarting(always_brake, episodes=1, seed=0, world={"rear_axle_offset": 1.5})
    assert seen == [1.5]
    argv = ["planner_quality.py", "--model", "search", "--set", "rear_axle_offset=3"]
    monkeypatch.setattr("sys.argv", argv)
    with pytest.raises(SystemExit) as error:
        planner_quality.main()
    assert error.value.code == 2


def test_brake_behind_is_refused_for_a_planner_other_than_search(planner_quality, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["planner_quality.py", "--model", "scripted", "--brake-behind"])
    with pytest.raises(SystemExit) as error:
        planner_quality.main()
    assert error.value.code == 2
    assert "--brake-behind applies to --model search only" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--model", "search", "--brake-behind", "--brake-behind-heading", "-1"],
            "brake_behind_heading must be",
        ),
        (
            ["--model", "search", "--max-lateral-acceleration", "0"],
            "max_lateral_acceleration must be positive",
        ),
    ],
)
def test_bad_expert_settings_end_in_one_line(planner_quality, monkeypatch, capsys, argv, message):
    monkeypatch.setattr("sys.argv", ["planner_quality.py", *argv])
    with pytest.raises(SystemExit) as error:
        planner_quality.main()
    assert error.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
