"""A saved MaskablePPO policy as a plain callable: its actions, and no global torch setting."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import torch as th
from sb3_contrib import MaskablePPO

from sb3_gccp.frozen import FrozenPolicy, load_frozen_policy

PLANNER = Path(__file__).resolve().parents[1] / "pretrained" / "planner.zip"


def test_a_frozen_policy_acts_as_predict_does_and_leaves_torch_threads_alone():
    th.set_num_threads(3)
    frozen = FrozenPolicy(PLANNER)
    assert th.get_num_threads() == 3
    model = MaskablePPO.load(PLANNER, device="cpu")
    env = gym.make("GCCPPlanner-v0", spawn_probability=0.2)
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        mask = env.unwrapped.action_masks()
        action, _ = model.predict(obs, action_masks=mask, deterministic=True)
        assert frozen(obs, mask) == int(action)
        obs, *_ = env.step(int(action))


def test_the_option_envs_planner_is_loaded_once_per_process_and_path():
    assert load_frozen_policy(str(PLANNER)) is load_frozen_policy(str(PLANNER))
