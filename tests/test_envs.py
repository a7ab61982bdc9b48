"""The three registered envs: API checkers, seeding, bad input, episode ends and info."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from helpers import place_ego
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from gccp_envs import ENV_IDS
from gccp_envs.action import EgoAction
from gccp_envs.config import IntersectionConfig

ALL_ENVS = sorted(ENV_IDS)
GOAL_KEY = {"GCCPPlanner-v0": "goal", "GCCPFlat-v0": "goal", "GCCPDecider-v0": "subgoals"}


def make(env_id, **kwargs):
    return gym.make(env_id, **kwargs).unwrapped


def test_importing_sb3_gccp_registers_the_envs():
    code = (
        "import sb3_gccp, gymnasium as gym\n"
        "for env_id in ('GCCPPlanner-v0', 'GCCPDecider-v0', 'GCCPFlat-v0'):\n"
        "    gym.make(env_id)\n"
    )
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr


BLOCK_THE_AGENT = """
import importlib.abc, sys

class Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("sb3_gccp", "torch"):
            raise ImportError(f"the world imported {name}")
        return None

sys.meta_path.insert(0, Blocked())
"""


def test_the_world_needs_neither_the_agent_nor_torch():
    code = BLOCK_THE_AGENT + (
        "import gymnasium as gym, gccp_envs\n"
        "import gccp_envs.rendering, gccp_envs.scripted\n"
        "for env_id in gccp_envs.ENV_IDS:\n"
        "    gym.make(env_id).reset(seed=0)\n"
        "env = gym.make('GCCPDecider-v0', duration=1.0)\n"
        "env.reset(seed=0)\n"
        "env.step(0)\n"
        "assert not any(m.split('.')[0] in ('sb3_gccp', 'torch') for m in sys.modules)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    blocked = subprocess.run(
        [sys.executable, "-c", BLOCK_THE_AGENT + "import torch"], capture_output=True, text=True, timeout=60
    )
    assert "the world imported torch" in blocked.stderr  # the block itself works


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_gymnasium_env_checker(env_id):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gym_check_env(make(env_id), skip_render_check=True)
    messages = [str(w.message) for w in caught if not issubclass(w.category, DeprecationWarning)]
    assert messages == []


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_sb3_env_checker(env_id):
    with warnings.catch_warnings():
        # Advice about image-like observation spaces: the policies use custom feature extractors.
        warnings.simplefilter("ignore", UserWarning)
        sb3_check_env(make(env_id), warn=True)


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_observation_and_action_spaces(env_id):
    env = make(env_id, spawn_probability=0.1)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert info["task"] in ("left", "straight", "right")
    n = 12 if env_id == "GCCPDecider-v0" else 6
    assert env.action_space == gym.spaces.Discrete(n)
    assert obs[GOAL_KEY[env_id]].shape == ((12, 3) if env_id == "GCCPDecider-v0" else (3,))
    mask = env.action_masks()
    assert mask.shape == (n,) and mask.dtype == bool and mask.any()
    obs, reward, terminated, truncated, info = env.step(int(np.flatnonzero(mask)[0]))
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float)
    assert isinstance(terminated, bool) and isinstance(truncated, bool)
    assert reward == pytest.approx(sum(info["reward_terms"].values()))


def rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    rewards = []
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        out.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            break
    return out, rewards


def assert_same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.keys() == y.keys()
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)


@pytest.mark.parametrize(
    ("env_id", "actions"),
    [
        ("GCCPPlanner-v0", [1, 1, 0, 2, 3, 1, 1, 0, 1, 1, 4, 5] * 2),
        ("GCCPFlat-v0", [1, 0, 1, 2, 3, 1] * 3),
        ("GCCPDecider-v0", [3, 2, 7]),
    ],
)
def test_seeding_is_reproducible(env_id, actions):
    kwargs = {"spawn_probability": 0.2}
    obs_a, rew_a = rollout(make(env_id, **kwargs), 7, actions)
    obs_b, rew_b = rollout(make(env_id, **kwargs), 7, actions)
    assert_same(obs_a, obs_b)
    assert rew_a == rew_b
    obs_c, rew_c = rollout(make(env_id, **kwargs), 8, actions)
    assert not np.array_equal(obs_a[0]["history"], obs_c[0]["history"])
    assert rew_a != rew_c


def test_reset_with_the_same_seed_restarts_the_same_episode():
    env = make("GCCPPlanner-v0", spawn_probability=0.2)
    first, _ = rollout(env, 3, [1, 1, 1])
    rollout(env, 4, [0, 0])
    again, _ = rollout(env, 3, [1, 1, 1])
    assert_same(first, again)
    # Without a seed the next episode continues the generator: a different episode.
    obs, _ = env.reset()
    assert not np.array_equal(obs["history"], first[0]["history"])


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_unknown_task(env_id):
    with pytest.raises(ValueError, match="unknown task 'diagonal'"):
        gym.make(env_id, task="diagonal")
    env = make(env_id)
    with pytest.raises(ValueError, match="unknown task 'diagonal'"):
        env.reset(seed=0, options={"task": "diagonal"})


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_unknown_config_key(env_id):
    with pytest.raises(ValueError, match=r"spawn_probabilty.*did you mean 'spawn_probability'"):
        gym.make(env_id, spawn_probabilty=0.1)
    with pytest.raises(ValueError, match=r"spawn_probabilty.*did you mean 'spawn_probability'"):
        gym.make(env_id, config={"spawn_probabilty": 0.1})


def test_unknown_config_key_with_a_config_object():
    with pytest.raises(ValueError, match="did you mean 'spawn_probability'"):
        gym.make("GCCPPlanner-v0", config=IntersectionConfig(), spawn_probabilty=0.1)


def test_config_object_and_mapping():
    env = make("GCCPPlanner-v0", config=IntersectionConfig(task="left"), spawn_probability=0.0)
    assert env.config.task == "left" and env.config.spawn_probability == 0.0
    env = make("GCCPFlat-v0", config={"task": "right", "ego_start_speed": [2.0, 3.0]})
    assert env.config.ego_start_speed == (2.0, 3.0)
    _, info = env.reset(seed=0)
    assert info["task"] == "right"


@pytest.mark.parametrize("env_id", ALL_ENVS)
@pytest.mark.parametrize("action", [-1, 12, 1.5, "1", [1, 2], None])
def test_invalid_action(env_id, action):
    env = make(env_id, spawn_probability=0.0)
    env.reset(seed=0)
    if env_id != "GCCPDecider-v0" and action == 12:
        action = 6
    with pytest.raises(ValueError, match="invalid action"):
        env.step(action)
    assert env.world.steps == 0  # nothing happened


@pytest.mark.parametrize("action", [np.int64(2), np.array(2), np.array([2]), 2])
def test_integer_like_actions(action):
    env = make("GCCPPlanner-v0", spawn_probability=0.0)
    env.reset(seed=0)
    env.step(action)
    assert env.world.steps == 1


def test_unsupported_render_mode():
    from gccp_envs.planner_env import GCCPPlannerEnv

    with pytest.raises(ValueError, match="unsupported render_mode 'ansi'"):
        GCCPPlannerEnv(render_mode="ansi")
    assert make("GCCPPlanner-v0").render() is None


@pytest.mark.parametrize("env_id", ["GCCPPlanner-v0", "GCCPFlat-v0"])
def test_time_limit_truncates(env_id):
    env = make(env_id, spawn_probability=0.0, duration=1.0)
    env.reset(seed=0)
    for step in range(1, 11):
        _, _, terminated, truncated, info = env.step(EgoAction.SLOW_DOWN)
        assert not terminated
        assert truncated == (step == 10)
    assert info["timeout"] and not info["is_success"]
    assert {"task", "crashed", "offroad", "wrong_exit"} <= info.keys()


def test_decider_time_limit_truncates():
    env = make("GCCPDecider-v0", spawn_probability=0.0, duration=1.0)
    env.reset(seed=0)
    _, _, terminated, truncated, info = env.step(0)
    assert truncated and not terminated and info["timeout"]


@pytest.mark.parametrize("env_id", ALL_ENVS)
@pytest.mark.parametrize(("task", "success"), [("straight", True), ("left", False)])
def test_is_success_only_at_the_tasks_own_exit(env_id, task, success):
    env = make(env_id, spawn_probability=0.0)
    env.reset(seed=0, options={"task": task})
    place_ego(env.world, 6.0, -31.0, -np.pi / 2, 8.0)  # 2 m before the straight exit
    action = 3 if env_id == "GCCPDecider-v0" else EgoAction.KEEP_DIRECTION
    terminated = False
    for _ in range(4):
        _, _, terminated, _, info = env.step(action)
        if terminated:
            break
    assert terminated
    assert info["is_success"] is success
    assert info["wrong_exit"] is not success
    assert info["task"] == task


def test_planner_goal_is_a_candidate_and_changes_every_decision_period():
    env = make("GCCPPlanner-v0", spawn_probability=0.0, task="straight", hold_probability=0.0)
    env.reset(seed=1)
    world = env.world
    goal = env._subgoal.copy()
    assert np.any(np.all(world.subgoal_candidates() == goal, axis=1))
    for _ in range(9):
        obs, _, _, _, info = env.step(EgoAction.SLOW_DOWN)
        assert not info["goal_reached"]
        np.testing.assert_array_equal(env._subgoal, goal)
    env.step(EgoAction.SLOW_DOWN)
    assert world.steps == 10
    assert not np.array_equal(env._subgoal, goal)
    assert np.any(np.all(world.subgoal_candidates() == env._subgoal, axis=1))
    obs = env._observe()
    np.testing.assert_allclose(obs["goal"], env.observer.to_ego(env._subgoal))


def test_planner_goal_is_replaced_when_reached():
    env = make("GCCPPlanner-v0", spawn_probability=0.0, task="straight", hold_probability=0.0)
    env.reset(seed=1)
    ego = env.world.ego
    env._subgoal = np.array([ego.x + np.cos(ego.heading), ego.y + np.sin(ego.heading), ego.heading])
    goal = env._subgoal.copy()
    obs, _, _, _, info = env.step(EgoAction.KEEP_DIRECTION)
    assert info["goal_reached"] and env.world.steps == 1
    assert not np.array_equal(env._subgoal, goal)
    assert obs["goal"][0] > 0  # the new goal lies ahead


def test_planner_hold_subgoal_is_the_nearest_candidate_and_is_reached_only_standing():
    env = make(
        "GCCPPlanner-v0", spawn_probability=0.0, task="straight", hold_probability=1.0, hold_continue=1.0
    )
    env.reset(seed=1)
    world = env.world
    for _ in range(3):  # at every redraw the hold is the candidate nearest the ego
        candidates = world.subgoal_candidates()
        nearest = np.argmin(np.hypot(candidates[:, 0] - world.ego.x, candidates[:, 1] - world.ego.y))
        np.testing.assert_array_equal(env._subgoal, candidates[nearest])
        for _ in range(10):
            *_, info = env.step(EgoAction.KEEP_DIRECTION)
            assert not info["goal_reached"]  # driving past does not count
    for _ in range(30):
        *_, info = env.step(EgoAction.SLOW_DOWN)
    assert world.ego.speed == 0.0
    reached = []
    for _ in range(20):  # standing on the nearest lattice point: reached once per period
        *_, info = env.step(EgoAction.SLOW_DOWN)
        reached.append(info["goal_reached"])
    assert sum(reached) == 2


@pytest.mark.parametrize(("hold", "r_time"), [(1.0, 0.0), (0.0, -0.05)])
def test_planner_time_penalty_is_r_time_hold_while_holding(hold, r_time):
    env = make(
        "GCCPPlanner-v0", spawn_probability=0.0, task="straight", hold_probability=hold, hold_continue=1.0
    )
    env.reset(seed=1)
    for _ in range(15):
        *_, info = env.step(EgoAction.SLOW_DOWN)
        assert info["reward_terms"]["r_time"] == r_time


def test_planner_uniform_subgoals_lie_ahead_of_the_ego():
    env = make("GCCPPlanner-v0", spawn_probability=0.0, task="left", hold_probability=0.0)
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        for _ in range(40):
            if env.world.steps % 10 == 0:  # just drawn: ahead and beyond the reach radius
                assert obs["goal"][0] > 0 and np.hypot(*obs["goal"][:2]) > 2.0
            obs, _, terminated, truncated, _ = env.step(EgoAction.KEEP_DIRECTION)
            if terminated or truncated:
                break


def test_planner_without_holds_draws_new_subgoals():
    env = make("GCCPPlanner-v0", spawn_probability=0.0, task="straight", hold_probability=0.0)
    env.reset(seed=1)
    goals = set()
    for _ in range(60):
        env.step(EgoAction.KEEP_DIRECTION)
        goals.add(tuple(env._subgoal))
    assert len(goals) >= 3


def test_planner_action_masks_follow_the_world(make_world):
    env = make("GCCPPlanner-v0", spawn_probability=0.0)
    env.reset(seed=0)
    place_ego(env.world, 6.0, 50.0, -np.pi / 2 + 0.4, 8.0)
    np.testing.assert_array_equal(env.action_masks(), [False, False, False, False, True, False])
