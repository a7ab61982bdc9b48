"""The time-out benchmark's reasons for standing (benchmarks/timeouts.py), on an empty road."""

from __future__ import annotations

from types import SimpleNamespace

import gymnasium as gym
import numpy as np
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


def scene(ego_xy, car_xy, committed=None):
    """A stand-in for a decider env: a standing ego and one standing car; ``committed`` None for a
    traffic backend that reports no commitment (SUMO's, SMARTS's)."""
    traffic = SimpleNamespace(indices=np.array([0]), pose=np.array([[*car_xy, 0.0]]), speed=np.array([0.0]))
    if committed is not None:
        traffic.committed = np.array([committed])
    world = SimpleNamespace(
        ego=SimpleNamespace(x=ego_xy[0], y=ego_xy[1], speed=0.0),
        traffic=traffic,
        layout=SimpleNamespace(junction=10.0),
        config=SimpleNamespace(subgoal_reach_radius=2.0),
    )
    return SimpleNamespace(unwrapped=SimpleNamespace(world=world, subgoal=None))


def test_without_commitments_a_car_inside_the_junction_counts_as_committed(timeouts):
    assert timeouts.waiting_reason(scene((2.0, 6.0), (-2.0, 3.0))) == "standoff"
    assert timeouts.waiting_reason(scene((2.0, 6.0), (-2.0, 3.0), committed=False)) == "standoff"
    # Outside the junction, a car ahead of a queued ego that has not committed holds it in the queue.
    assert timeouts.waiting_reason(scene((2.0, 24.0), (2.0, 16.0))) == "queued"
    assert timeouts.waiting_reason(scene((2.0, 24.0), (2.0, 16.0), committed=True)) == "standoff"
