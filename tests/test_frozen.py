"""A saved MaskablePPO policy as a plain callable: its actions, and no global torch setting."""

from __future__ import annotations

import pickle
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig
from sb3_gccp.frozen import FrozenPolicy, load_frozen_planner, load_planner

PLANNER = Path(__file__).resolve().parents[1] / "pretrained" / "planner.zip"


def test_a_frozen_policy_acts_as_predict_does_and_leaves_torch_threads_alone():
    th.set_num_threads(3)
    frozen = load_planner(PLANNER, IntersectionConfig(spawn_probability=0.2))
    assert th.get_num_threads() == 3
    model = MaskablePPO.load(PLANNER, device="cpu")  # SB3's own loader, on a file we trust, as reference
    env = gym.make("GCCPPlanner-v0", spawn_probability=0.2)
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        mask = env.unwrapped.action_masks()
        action, _ = model.predict(obs, action_masks=mask, deterministic=True)
        assert frozen(obs, mask) == int(action)
        obs, *_ = env.step(int(action))


def test_the_traced_policies_take_predicts_actions_over_a_hierarchys_episodes():
    """The planner and the decider, their modules for the first calls and traced after them, against
    ``predict`` on the same observations: with the env's masks, without a mask, and with the most likely
    action masked out."""
    from sb3_gccp.hierarchy import load_hierarchy

    hierarchy = load_hierarchy(PLANNER.parent)
    env = hierarchy.make_env()
    decider = hierarchy.decider_policy(env.config)
    planner = env.planner
    planner._logits.after_calls = decider._logits.after_calls = 3
    references = {
        id(frozen): MaskablePPO.load(path, device="cpu")
        for frozen, path in ((planner, PLANNER), (decider, hierarchy.decider))
    }
    seen: list[tuple[FrozenPolicy, dict[str, np.ndarray], np.ndarray]] = []

    def recorded(frozen: FrozenPolicy) -> Callable[[dict[str, np.ndarray], np.ndarray], int]:
        def act(obs: dict[str, np.ndarray], mask: np.ndarray) -> int:
            seen.append((frozen, {key: value.copy() for key, value in obs.items()}, np.array(mask)))
            return frozen(obs, mask)

        return act

    env.planner = recorded(planner)
    act = recorded(decider)
    for seed in (3, 4):
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, _ = env.step(act(obs, env.action_masks()))
            done = terminated or truncated
    assert (
        sum(frozen is decider for frozen, _, _ in seen) > 5
        and sum(frozen is planner for frozen, _, _ in seen) > 50
    )
    for frozen, obs, mask in seen:
        model = references[id(frozen)]
        for given in (mask, None):
            action, _ = model.predict(obs, action_masks=given, deterministic=True)
            assert frozen(obs, given) == int(action)
        first, _ = model.predict(obs, deterministic=True)
        without_first = np.ones_like(mask)
        without_first[int(first)] = False
        action, _ = model.predict(obs, action_masks=without_first, deterministic=True)
        assert frozen(obs, without_first) == int(action) != int(first)
    assert len(planner._logits._traced) == len(decider._logits._traced) == 1  # one per observation shape
    assert pickle.loads(pickle.dumps(planner))(*seen[-1][1:]) == planner(*seen[-1][1:])


def test_the_option_envs_planner_is_loaded_once_per_process_path_and_world():
    world = IntersectionConfig()
    assert load_frozen_planner(str(PLANNER), world) is load_frozen_planner(str(PLANNER), world)
    assert load_frozen_planner(str(PLANNER), world.replace(duration=5.0)) is not load_frozen_planner(
        str(PLANNER), world
    )


def test_the_option_env_runs_a_maskable_ppo_planner_loaded_from_a_zip():
    from gccp_envs.option_env import GCCPDeciderEnv

    env = GCCPDeciderEnv(planner=load_planner(PLANNER, IntersectionConfig()), spawn_probability=0.0)
    poses = []
    env.set_planner_step_callback(lambda e: poses.append(e.world.ego.as_array()))
    obs, _ = env.reset(seed=1, options={"task": "straight"})
    start = env.world.ego.as_array()
    _, _, terminated, _, info = env.step(int(obs["subgoals"][:, 0].argmax()))  # the farthest ahead
    assert len(poses) == env.config.decision_period and not terminated
    assert np.hypot(*(poses[-1][:2] - start[:2])) > 5.0  # it drove on towards the subgoal
    assert info["subgoal_reached"] or poses[-1][3] > 4.0


def test_the_shipped_hierarchy_runs_its_learned_planner():
    from sb3_gccp.hierarchy import load_hierarchy

    hierarchy = load_hierarchy(PLANNER.parent)
    assert hierarchy.planner == PLANNER and hierarchy.overrides == {}
    env = hierarchy.make_env({"spawn_probability": 0.0})
    assert isinstance(env.planner, FrozenPolicy)
