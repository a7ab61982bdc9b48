"""The time-out benchmark's reasons for standing (benchmarks/timeouts.py), on an empty road."""

from __future__ import annotations

import gymnasium as gym
import pytest
from helpers import always_brake, load_benchmark

from gccp_envs.scripted import FarthestSubgoalDecider, ScriptedPlanner


@pytest.fixture(scope="module")
def timeouts():
    return load_benchmark("timeouts")


def standing_start(planner):
    """A decider env on an empty road whose ego starts at rest, and its first observation."""
    env = gym.make(
        "GCCPDecider-v0", task="straight", spawn_probability=0.0, ego_start_standing=1.0, planner=planner
    )
    obs, _ = env.reset(seed=0)
    return env, obs


def test_a_planner_that_stands_when_sent_beyond_reach_stalls(timeouts):
    env, obs = standing_start(always_brake)
    assert env.unwrapped.world.ego.speed == 0.0
    assert timeouts.waiting_reason(env) == "other"  # no option yet: nothing was asked of the planner
    env.step(FarthestSubgoalDecider()(obs))
    assert env.unwrapped.world.ego.speed == 0.0
    assert timeouts.waiting_reason(env) == "stall"


def test_a_planner_that_drives_there_is_not_waiting(timeouts):
    env, obs = standing_start(None)
    env.unwrapped.planner = ScriptedPlanner(env.unwrapped.config)
    env.step(FarthestSubgoalDecider()(obs))
    assert env.unwrapped.world.ego.speed > 0.5
    assert timeouts.waiting_reason(env) is None
