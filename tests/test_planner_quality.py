"""The planner benchmark's restart test (benchmarks/planner_quality.py), on empty roads and in traffic."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from helpers import always_brake, load_benchmark

from gccp_envs.config import IntersectionConfig
from gccp_envs.scripted import SearchPlanner
from sb3_gccp.hierarchy import Hierarchy


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


PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"


def test_a_planner_named_by_the_hierarchy_beside_it_is_measured_in_that_hierarchys_world(
    planner_quality, tmp_path
):
    world, spec = planner_quality.hierarchy_world(str(PRETRAINED / "planner.zip"))
    assert spec == PRETRAINED / "hierarchy.yml"
    assert world == Hierarchy.read(PRETRAINED).world
    assert world["mask_drive_on"] > 0.0  # the key the planner entry trains it with
    shutil.copyfile(PRETRAINED / "planner.zip", tmp_path / "planner.zip")
    assert planner_quality.hierarchy_world(str(tmp_path / "planner.zip")) == ({}, None)
    assert planner_quality.hierarchy_world("search") == ({}, None)


@pytest.mark.parametrize("default_world", [False, True])
def test_the_benchmark_runs_in_the_world_it_reads_with_set_on_top(
    planner_quality, monkeypatch, default_world
):
    """The hierarchy's world reaches the benchmark's parts, --set on top; --default-world drops it."""

    class Seen(Exception):
        pass

    def first_part(planner, episodes, seed, hold_steps, oracle, world):
        raise Seen(world)

    monkeypatch.setattr(planner_quality, "subgoal_reaching", first_part)
    argv = ["planner_quality.py", "--model", str(PRETRAINED / "planner.zip"), "--set", "rear_axle_offset=0.5"]
    monkeypatch.setattr("sys.argv", argv + ["--default-world"] * default_world)
    with pytest.raises(Seen) as seen:
        planner_quality.main()
    world = seen.value.args[0]
    if default_world:
        assert world == {"rear_axle_offset": 0.5}
    else:
        assert world == {**Hierarchy.read(PRETRAINED).world, "rear_axle_offset": 0.5}
