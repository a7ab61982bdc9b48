"""A saved MaskablePPO policy as a plain callable: its actions, and no global torch setting."""

from __future__ import annotations

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
