"""The ceiling on success set by the flows alone (benchmarks/winnable.py), on our traffic and SUMO's."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import load_benchmark

from gccp_envs.config import DT, IntersectionConfig


@pytest.fixture(scope="module")
def winnable():
    return load_benchmark("winnable")


def run(winnable, monkeypatch, capsys, *argv: str) -> str:
    monkeypatch.setattr(sys, "argv", ["winnable.py", *argv])
    winnable.main()
    return capsys.readouterr().out


def test_least_exit_time_accelerates_from_standing(winnable):
    config = IntersectionConfig()
    seconds = winnable.least_exit_time(config, 100.0)
    to_cruise = config.cruise_speed / config.acceleration
    # Accelerating to cruise speed, then cruising: the closed form, to within a step.
    closed = to_cruise + (100.0 - 0.5 * config.acceleration * to_cruise**2) / config.cruise_speed
    assert abs(seconds - closed) <= 2 * DT


def test_a_backend_without_commitments_commits_a_car_at_its_stop_line(winnable):
    traffic = SimpleNamespace(s=np.array([10.0, 18.0]), length=np.array([5.0, 5.0]))
    world = SimpleNamespace(traffic=traffic, layout=SimpleNamespace(stop_s=20.0))
    np.testing.assert_array_equal(winnable.committed(world, np.array([0, 1])), [False, True])
    traffic.committed = np.array([True, False])  # ours reports its own
    np.testing.assert_array_equal(winnable.committed(world, np.array([0, 1])), [True, False])


def test_our_flows_are_all_winnable(winnable, monkeypatch, capsys):
    out = run(winnable, monkeypatch, capsys, "--tasks", "left", "--episodes-per-task", "4")
    assert out.splitlines()[-1] == "max_success 1.000"


def test_on_sumos_traffic_a_head_that_never_gets_its_gap_makes_a_flow_unwinnable(
    winnable, monkeypatch, capsys
):
    out = run(
        winnable, monkeypatch, capsys, "--tasks", "left", "--episodes-per-task", "4", "--set", "traffic=sumo"
    )
    assert "left seed 3: unwinnable (head of queue commits: lane 0 never" in out
    assert out.splitlines()[-1] == "max_success 0.750"


def test_a_bad_key_is_one_line_and_exit_2(winnable, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run(winnable, monkeypatch, capsys, "--set", "bogus=1")
    assert exit_info.value.code == 2
    assert "unknown intersection config key(s): 'bogus'" in capsys.readouterr().err
