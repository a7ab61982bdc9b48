"""Masked baselines: a masked action is never taken, in training or in evaluation; the wrong-exit penalty;
the paper-style rows keep neither."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from gccp_envs.config import IntersectionConfig
from gccp_envs.rewards import planner_reward
from sb3_gccp.action_masks import ACTION_MASK_KEY, ActionMaskObservation, mask_values
from sb3_gccp.maskable_dqn import MaskableDQN
from sb3_gccp.reproduce.methods import METHODS
from sb3_gccp.reproduce.plan import PRESETS, method_settings
from sb3_gccp.sac_discrete import SACDiscrete

N_ACTIONS = 6


class RandomMaskEnv(gym.Env):
    """Dict observations, six actions of which a random one to four are allowed each step; it counts the
    masked actions it is given. Reward 1 for action 0 when allowed, so the greedy values favour an action
    that is often masked."""

    def __init__(self) -> None:
        self.observation_space = spaces.Dict({"x": spaces.Box(-1.0, 1.0, (3,), np.float32)})
        self.action_space = spaces.Discrete(N_ACTIONS)
        self.violations = 0
        self.steps = 0
        self._mask = np.ones(N_ACTIONS, dtype=bool)

    def _draw(self) -> dict[str, np.ndarray]:
        self._mask = np.zeros(N_ACTIONS, dtype=bool)
        allowed = self.np_random.choice(N_ACTIONS, size=int(self.np_random.integers(1, 5)), replace=False)
        self._mask[allowed] = True
        return {"x": self.np_random.uniform(-1, 1, 3).astype(np.float32)}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self._draw(), {}

    def step(self, action):
        self.steps += 1
        self.violations += int(not self._mask[int(action)])
        reward = float(int(action) == 0)
        return self._draw(), reward, False, self.steps % 20 == 0, {}

    def action_masks(self) -> np.ndarray:
        return self._mask.copy()


def _train(algorithm, masked: bool, **kwargs):
    env = RandomMaskEnv()
    wrapped = ActionMaskObservation(env) if masked else env
    model = algorithm(
        "MultiInputPolicy",
        wrapped,
        learning_starts=50,
        buffer_size=500,
        batch_size=16,
        policy_kwargs={"net_arch": [16]},
        seed=0,
        device="cpu",
        **kwargs,
    )
    model.learn(400)
    return model, env, wrapped


def _evaluation_violations(model, env, wrapped, steps: int = 200) -> int:
    env.violations = 0
    obs, _ = wrapped.reset(seed=1)
    for _ in range(steps):
        action, _ = model.predict(obs, deterministic=True)
        obs, _, _, _, _ = wrapped.step(action)
    return env.violations


@pytest.mark.parametrize(
    "algorithm, kwargs",
    [
        (MaskableDQN, {"exploration_fraction": 0.5, "exploration_final_eps": 0.3, "train_freq": 4}),
        (SACDiscrete, {}),
    ],
)
def test_a_masked_action_is_never_taken(algorithm, kwargs):
    model, env, wrapped = _train(algorithm, True, **kwargs)
    assert env.steps == 400 and env.violations == 0  # warm-up, exploration and learning steps
    assert _evaluation_violations(model, env, wrapped) == 0


def test_without_masks_the_same_run_takes_masked_actions():
    """The check above can fail: unmasked DQN on the same env takes masked actions."""
    _, env, _ = _train(MaskableDQN, False, exploration_fraction=0.5)
    assert env.violations > 0


def test_masked_values_never_win_and_have_no_probability():
    values = th.tensor([[5.0, 1.0, -2.0], [0.0, 9.0, 3.0]])
    obs = {ACTION_MASK_KEY: th.tensor([[0, 1, 1], [1, 0, 1]], dtype=th.int8)}
    masked = mask_values(values, obs)
    assert masked.argmax(dim=1).tolist() == [1, 2]
    probs = th.softmax(masked, dim=1)
    assert probs[0, 0] == 0 and probs[1, 1] == 0 and th.isfinite((probs * th.log_softmax(masked, 1)).sum())
    assert th.equal(mask_values(values, {"x": values}), values)  # no mask: unchanged


def test_dqn_bootstraps_from_allowed_actions_only():
    model, _, wrapped = _train(MaskableDQN, True)
    obs, _ = wrapped.reset(seed=3)
    tensor = {k: th.as_tensor(v)[None] for k, v in obs.items()}
    q = model.q_net_target(tensor)[0]
    allowed = obs[ACTION_MASK_KEY].astype(bool)
    assert q.max() == q[th.as_tensor(allowed)].max() and (q[th.as_tensor(~allowed)] < -1e7).all()


def test_leaving_by_another_exit_pays_the_off_road_penalty():
    on = IntersectionConfig()
    off = IntersectionConfig(wrong_exit_penalty=False)
    wrong = planner_reward(on, (1.0, 0.0), (1.0, 0.0), False, False, False, wrong_exit=True)
    assert wrong["r_off"] == on.r_off == -1.0
    assert planner_reward(off, (1.0, 0.0), (1.0, 0.0), False, False, False, wrong_exit=True)["r_off"] == 0.0
    assert planner_reward(on, (1.0, 0.0), (1.0, 0.0), False, False, False)["r_off"] == 0.0


def test_the_flat_env_ends_a_wrong_exit_with_the_penalty():
    """Drive straight through on a left-turn task: the episode ends at the opposite exit, paid r_off."""
    env = gym.make(
        "GCCPFlat-v0", config=IntersectionConfig(task="left", spawn_probability=0.0, duration=30.0)
    )
    env.reset(seed=0)
    info: dict = {}
    for _ in range(300):
        _, _, terminated, truncated, info = env.step(1)  # keep direction
        if terminated or truncated:
            break
    assert info.get("wrong_exit") and info["reward_terms"]["r_off"] == -1.0
    env.close()


def test_paper_style_rows_have_neither_masks_nor_the_penalty():
    preset = PRESETS["quick"]
    for name in ("dqn", "ppo", "sac_discrete"):
        masked = method_settings(METHODS[name], preset)
        paper = method_settings(METHODS[f"{name}_paper"], preset)
        assert masked["action_masks"] is True and "wrong_exit_penalty" not in (masked.get("env_kwargs") or {})
        assert paper["action_masks"] is False and paper["env_kwargs"]["wrong_exit_penalty"] is False
        assert {k: v for k, v in masked.items() if k not in ("action_masks", "env_kwargs")} == {
            k: v for k, v in paper.items() if k not in ("action_masks", "env_kwargs")
        }
