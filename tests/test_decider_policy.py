"""The decision-maker policy: the paper's per-subgoal heads, masks, save/load and a tiny run."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from sb3_contrib import MaskablePPO
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.utils import obs_as_tensor
from test_policies import TINY_ENCODER
from torch import nn

from sb3_gccp.policies import DeciderFeaturesExtractor, DecisionMakerPolicy, SubgoalHeads

TINY_DECIDER = {"encoder": TINY_ENCODER, "net_arch": {"pi": [16, 16], "vf": [8, 16]}}


@pytest.fixture(scope="module")
def env() -> gym.Env:
    return gym.make("GCCPDecider-v0", spawn_probability=0.02)


@pytest.fixture(scope="module")
def batch(env) -> dict[str, th.Tensor]:
    obs, _ = env.reset(seed=1)
    stacked = [obs]
    for action in range(7):
        obs, _, terminated, truncated, _ = env.step(action % 12)
        if terminated or truncated:
            obs, _ = env.reset()
        stacked.append(obs)
    raw = {key: np.stack([o[key] for o in stacked]) for key in stacked[0]}
    tensors = preprocess_obs(obs_as_tensor(raw, "cpu"), env.observation_space)
    assert isinstance(tensors, dict)
    return tensors


def policy_for(env: gym.Env, **kwargs) -> DecisionMakerPolicy:
    return DecisionMakerPolicy(env.observation_space, env.action_space, lambda _: 1e-4, **kwargs)


def test_features_are_the_state_feature_then_one_feature_per_subgoal(env, batch):
    extractor = DeciderFeaturesExtractor(env.observation_space, encoder=TINY_ENCODER)
    assert extractor.features_dim == 5 * 16 + 12 * 16
    out = extractor(batch)
    scene = extractor.encoder.encode(batch)
    state = extractor.encoder.ego_features(scene, extractor.encoder.goal_features(batch["task_goal"]))
    th.testing.assert_close(out[:, :80], state)
    first = extractor.subgoal_encoder(batch["subgoals"][:, 0] * extractor.encoder.goal_scale)
    th.testing.assert_close(out[:, 80:96], first)


def test_the_checks_verdict_enters_each_subgoal_feature():
    env = gym.make("GCCPDecider-v0", spawn_probability=0.02, observe_mask=True)
    obs, _ = env.reset(seed=1)
    extractor = DeciderFeaturesExtractor(env.observation_space, encoder=TINY_ENCODER)
    closed = {**obs, "subgoal_allowed": np.where(np.arange(12) == 4, 0.0, 1.0).astype(np.float32)}
    raw = {key: np.stack([obs[key], closed[key]]) for key in obs}
    out = extractor(preprocess_obs(obs_as_tensor(raw, "cpu"), env.observation_space))
    per_subgoal = (out[0, 80:] - out[1, 80:]).abs().view(12, 16).sum(-1)
    assert per_subgoal[4] > 0
    assert per_subgoal[np.arange(12) != 4].max() == 0
    th.testing.assert_close(out[0, :80], out[1, :80])


def test_default_heads_have_the_papers_depths(env):
    policy = policy_for(env)
    heads = policy.mlp_extractor
    assert isinstance(heads, SubgoalHeads)

    def linear(module):
        return [m.out_features for m in module.modules() if isinstance(m, nn.Linear)]

    # Logit: 3-layer MLP per subgoal (two hidden layers, then the shared one-logit layer).
    assert linear(heads.policy_net) + linear(policy.action_net) == [256, 256, 1]
    # Value: 2-layer MLP per subgoal to L, then a 2-layer MLP over the flattened N x L to one value.
    assert linear(heads.subgoal_value_net) == [256, 128]
    assert [*linear(heads.value_net), policy.value_net.out_features] == [256, 1]


def test_each_logit_depends_only_on_its_own_subgoal(env, batch):
    th.manual_seed(0)
    policy = policy_for(env, **TINY_DECIDER)
    moved = dict(batch)
    moved["subgoals"] = batch["subgoals"].clone()
    moved["subgoals"][:, 4] += 3.0

    def logits(obs: dict[str, th.Tensor]) -> th.Tensor:
        return policy.action_net(policy.mlp_extractor.forward_actor(policy.extract_features(obs)))

    with th.no_grad():
        before, changed = logits(batch), logits(moved)
        values, moved_values = policy.predict_values(batch), policy.predict_values(moved)
    assert before.shape == (8, 12)
    differs = ~th.isclose(before, changed, atol=1e-6)
    assert differs[:, 4].all() and not differs[:, np.r_[0:4, 5:12]].any()
    assert not th.allclose(values, moved_values)  # the value sees every subgoal


def test_sampled_subgoals_respect_the_masks(env, batch):
    policy = policy_for(env, **TINY_DECIDER)
    rng = np.random.default_rng(0)
    for _ in range(5):
        masks = rng.random((8, 12)) < 0.2
        masks[np.arange(8), rng.integers(0, 12, 8)] = True
        with th.no_grad():
            actions, _, _ = policy(batch, action_masks=masks)
        assert masks[np.arange(8), actions.numpy()].all()


def test_bad_net_arch_is_rejected(env):
    with pytest.raises(ValueError, match="vf: \\[h_subgoal, h_value\\]"):
        policy_for(env, net_arch={"pi": [16], "vf": [16]})


def test_tiny_run_saves_and_loads_by_alias(env, tmp_path):
    from sb3_gccp.hyperparams import resolve_class

    assert resolve_class("DecisionMakerPolicy") is DecisionMakerPolicy
    model = MaskablePPO(DecisionMakerPolicy, env, policy_kwargs=TINY_DECIDER, n_steps=8, batch_size=8, seed=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(8)
    after = list(model.policy.parameters())
    assert any(not th.equal(p, q) for p, q in zip(before, after, strict=True))
    # The optimiser holds exactly the policy's parameters (the replaced action_net included).
    optimised = {id(p) for group in model.policy.optimizer.param_groups for p in group["params"]}
    assert optimised == {id(p) for p in model.policy.parameters()}
    model.save(tmp_path / "decider.zip")
    loaded = MaskablePPO.load(tmp_path / "decider.zip")
    obs, _ = env.reset(seed=3)
    mask = np.zeros(12, bool)
    mask[5] = True
    action, _ = loaded.predict(obs, action_masks=mask)
    assert int(action) == 5
