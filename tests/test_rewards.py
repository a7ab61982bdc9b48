"""Every reward term with the paper's constants, alone and as paid by the envs."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from helpers import path_pose, place_ego, place_ego_on_path

from gccp_envs.action import EgoAction, EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.rewards import decider_reward, goal_errors, goal_reached, planner_reward

CFG = IntersectionConfig()


def test_goal_errors():
    ego = EgoState(1.0, 2.0, np.pi - 0.1, 3.0)
    distance, heading = goal_errors(ego, np.array([4.0, 6.0, -np.pi + 0.1]))
    assert distance == pytest.approx(5.0)
    assert heading == pytest.approx(0.2)  # across the +-pi seam
    assert goal_errors(ego, np.array([1.0, 2.0, np.pi - 0.6]))[1] == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("errors", "reached"),
    [
        ((0.0, 0.0), True),
        ((2.0, 0.5), True),
        ((2.01, 0.0), False),
        ((0.0, 0.51), False),
    ],
)
def test_goal_reached(errors, reached):
    assert goal_reached(CFG, errors) is reached


def test_planner_reward_terms():
    terms = planner_reward(
        CFG, before=(10.0, 0.4), after=(9.2, 0.3), arrived=False, crashed=False, offroad=False
    )
    assert terms == pytest.approx(
        {"r_time": -0.05, "r_arr": 0.0, "r_col": 0.0, "r_off": 0.0, "r_dist": 0.05 * 0.8, "r_head": 0.5 * 0.1}
    )
    terms = planner_reward(CFG, (1.0, 0.0), (1.5, 0.2), arrived=True, crashed=True, offroad=True)
    assert terms == pytest.approx(
        {
            "r_time": -0.05,
            "r_arr": 1.0,
            "r_col": -1.0,
            "r_off": -1.0,
            "r_dist": -0.05 * 0.5,
            "r_head": -0.5 * 0.2,
        }
    )


def test_decider_reward_terms():
    assert decider_reward(CFG, False, False, 0.0) == pytest.approx(
        {"r_goal": 0.0, "r_subgoal": 0.0, "r_subgoal_dist": -0.5}
    )
    assert decider_reward(CFG, True, True, 12.0) == pytest.approx(
        {"r_goal": 3.0, "r_subgoal": 0.5, "r_subgoal_dist": -0.5 + 0.05 * 12.0}
    )


def test_reward_constants_come_from_the_config():
    cfg = CFG.replace(r_time=-1.0, eps_d=2.0, r_near=0.0, eps_s=1.0)
    assert planner_reward(cfg, (3.0, 0.0), (1.0, 0.0), False, False, False)["r_dist"] == pytest.approx(4.0)
    assert planner_reward(cfg, (3.0, 0.0), (1.0, 0.0), False, False, False)["r_time"] == -1.0
    assert decider_reward(cfg, False, False, 7.0)["r_subgoal_dist"] == pytest.approx(7.0)


# --- as paid by the envs -------------------------------------------------------------------------------
def planner_env(env_id="GCCPPlanner-v0", seed=0, task="straight"):
    env = gym.make(env_id, spawn_probability=0.0, task=task).unwrapped
    env.reset(seed=seed)
    return env


def test_planner_env_progress_terms_match_the_observed_goal():
    env = planner_env()
    obs, _ = env.reset(seed=5)
    before = obs["goal"].astype(float)
    obs, reward, terminated, truncated, info = env.step(EgoAction.SLOWLY_TURN_RIGHT)
    after = obs["goal"].astype(float)  # the same subgoal, seen from the new pose
    terms = info["reward_terms"]
    assert not terminated and not truncated
    assert terms["r_time"] == -0.05
    assert terms["r_dist"] == pytest.approx(0.05 * (np.hypot(*before[:2]) - np.hypot(*after[:2])), abs=1e-5)
    assert terms["r_head"] == pytest.approx(0.5 * (abs(before[2]) - abs(after[2])), abs=1e-5)
    assert reward == pytest.approx(sum(terms.values()))
    assert terms["r_col"] == terms["r_off"] == 0.0


def test_planner_env_pays_arrival_once_per_goal():
    env = planner_env()
    world = env.world
    place_ego_on_path(world, 2, 40.0, 0.0)
    env._subgoal = path_pose(world.layout, 2, 40.5)  # right in front of the stopped ego
    env._arrived = False
    _, reward, _, _, info = env.step(EgoAction.SLOW_DOWN)
    assert info["goal_reached"] and info["reward_terms"]["r_arr"] == 1.0
    assert reward == pytest.approx(1.0 - 0.05)
    _, _, _, _, info = env.step(EgoAction.SLOW_DOWN)
    assert not info["goal_reached"] and info["reward_terms"]["r_arr"] == 0.0


def test_planner_env_collision_penalty():
    env = planner_env()
    world = env.world
    place_ego_on_path(world, 2, 40.0, 5.0)
    assert world.traffic.spawn(2, 44.0, speed=0.0) is not None
    _, reward, terminated, truncated, info = env.step(EgoAction.KEEP_DIRECTION)
    assert terminated and not truncated
    assert info["crashed"] and info["reward_terms"]["r_col"] == -1.0
    assert not info["is_success"]
    assert reward < -1.0


def test_planner_env_off_road_penalty():
    env = planner_env()
    place_ego(env.world, 7.0, 50.0, -np.pi / 2 + 0.3, 8.0)  # at the right kerb, heading off the road
    _, _, terminated, _, info = env.step(EgoAction.QUICKLY_TURN_RIGHT)
    assert terminated and info["offroad"]
    assert info["reward_terms"]["r_off"] == -1.0
    assert info["reward_terms"]["r_col"] == 0.0


def test_flat_env_pays_arrival_at_the_task_exit_only():
    env = planner_env("GCCPFlat-v0")
    env.reset(seed=0)
    np.testing.assert_allclose(env._subgoal, env.world.task_goal)
    _, _, _, _, info = env.step(EgoAction.KEEP_DIRECTION)
    assert info["reward_terms"]["r_arr"] == 0.0
    place_ego(env.world, 6.0, -32.5, -np.pi / 2, 8.0)  # 0.5 m before the straight exit
    _, _, terminated, _, info = env.step(EgoAction.KEEP_DIRECTION)
    assert terminated and info["is_success"]
    assert info["reward_terms"]["r_arr"] == 1.0


def decider_env(seed=0):
    env = gym.make("GCCPDecider-v0", spawn_probability=0.0, task="straight").unwrapped
    env.reset(seed=seed)
    return env


def test_decider_reward_for_a_reached_subgoal():
    env = decider_env()
    place_ego_on_path(env.world, 2, 45.0, 0.0)  # on a lattice point: candidate 0 is the ego's pose
    obs = env._observe()
    np.testing.assert_allclose(obs["subgoals"][0], 0.0, atol=1e-5)
    _, reward, terminated, _, info = env.step(0)
    assert not terminated
    assert info["subgoal_reached"]
    assert info["reward_terms"] == pytest.approx({"r_goal": 0.0, "r_subgoal": 0.5, "r_subgoal_dist": -0.5})
    assert reward == pytest.approx(0.0)


def test_decider_reward_for_a_far_subgoal():
    env = decider_env()
    place_ego_on_path(env.world, 2, 45.0, 0.0)
    obs = env._observe()
    distance = float(np.hypot(*obs["subgoals"][3, :2]))
    assert distance == pytest.approx(15.0, abs=1e-4)
    _, reward, _, _, info = env.step(3)
    assert not info["subgoal_reached"]  # a standing start covers about 1 m in 1 s
    assert info["reward_terms"] == pytest.approx(
        {"r_goal": 0.0, "r_subgoal": 0.0, "r_subgoal_dist": -0.5 + 0.05 * 15.0}, abs=1e-5
    )
    assert reward == pytest.approx(0.25, abs=1e-5)


def test_decider_reward_for_the_task_goal():
    env = decider_env()
    place_ego(env.world, 6.0, -30.0, -np.pi / 2, 8.0)  # 3 m before the straight exit
    _, _, terminated, truncated, info = env.step(3)
    assert terminated and not truncated
    assert info["is_success"]
    assert info["reward_terms"]["r_goal"] == 3.0
    assert env.world.steps < 10  # the option ended early
