"""The motion-planner policy: SB3 integration, action masks, save/load in a fresh process, a tiny run."""

from __future__ import annotations

import subprocess
import sys
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from helpers import TINY_ENCODER
from sb3_contrib import MaskablePPO
from stable_baselines3.common.preprocessing import is_image_space, preprocess_obs
from stable_baselines3.common.utils import obs_as_tensor
from torch import nn

from sb3_gccp.policies import MotionPlannerPolicy, PlannerFeaturesExtractor

TINY_POLICY = {"encoder": TINY_ENCODER, "net_arch": {"pi": [16], "vf": [16]}}
WORLD = {"spawn_probability": 0.0}


@pytest.fixture(scope="module")
def env() -> gym.Env:
    return gym.make("GCCPPlanner-v0", **WORLD)


def observations(env: gym.Env, count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``count`` stacked observations of one episode (reset when it ends)."""
    obs, _ = env.reset(seed=seed)
    batch = [obs]
    while len(batch) < count:
        obs, _, terminated, truncated, _ = env.step(1)
        if terminated or truncated:
            obs, _ = env.reset()
        batch.append(obs)
    return {key: np.stack([o[key] for o in batch]) for key in batch[0]}


def test_bev_is_not_treated_as_an_image(env):
    space = env.observation_space
    assert not is_image_space(space["bev"])
    obs = obs_as_tensor(observations(env, 2), "cpu")
    bev = preprocess_obs(obs, space, normalize_images=True)["bev"]
    assert bev.dtype == th.float32
    assert bev.max() == 1.0 and bev.min() == 0.0


def test_features_extractor_returns_the_ego_feature(env):
    extractor = PlannerFeaturesExtractor(env.observation_space, encoder=TINY_ENCODER)
    assert extractor.features_dim == 80
    obs = preprocess_obs(obs_as_tensor(observations(env, 3), "cpu"), env.observation_space)
    assert isinstance(obs, dict)
    out = extractor(obs)
    scene = extractor.encoder.encode(obs)
    th.testing.assert_close(
        out, extractor.encoder.ego_features(scene, extractor.encoder.goal_features(obs["goal"]))
    )
    assert out.shape == (3, 80)


def test_default_policy_has_the_papers_heads(env):
    policy = MotionPlannerPolicy(env.observation_space, env.action_space, lambda _: 1e-4)
    assert isinstance(policy.features_extractor, PlannerFeaturesExtractor)
    assert policy.features_dim == 5 * 128
    for head, out in (
        (policy.mlp_extractor.policy_net, policy.action_net),
        (policy.mlp_extractor.value_net, policy.value_net),
    ):
        linears = [m for m in head if isinstance(m, nn.Linear)] + [out]
        assert [layer.out_features for layer in linears] == [256, 256, out.out_features]
        assert all(isinstance(m, nn.ReLU) for m in head if not isinstance(m, nn.Linear))
    assert policy.action_net.out_features == 6 and policy.value_net.out_features == 1


def test_encoder_kwarg_and_features_extractor_kwargs_both_set_the_sizes(env):
    by_encoder = MotionPlannerPolicy(env.observation_space, env.action_space, lambda _: 1e-4, **TINY_POLICY)
    by_kwargs = MotionPlannerPolicy(
        env.observation_space,
        env.action_space,
        lambda _: 1e-4,
        features_extractor_kwargs={"encoder": TINY_ENCODER},
    )
    assert by_encoder.features_dim == by_kwargs.features_dim == 80
    with pytest.raises(ValueError, match="unknown encoder config key"):
        MotionPlannerPolicy(env.observation_space, env.action_space, lambda _: 1e-4, encoder={"width": 3})


def test_sampled_actions_respect_the_action_masks(env):
    th.manual_seed(0)
    policy = MotionPlannerPolicy(env.observation_space, env.action_space, lambda _: 1e-4, **TINY_POLICY)
    obs = obs_as_tensor(observations(env, 64), "cpu")
    rng = np.random.default_rng(0)
    for _ in range(5):
        masks = rng.random((64, 6)) < 0.3
        masks[np.arange(64), rng.integers(0, 6, 64)] = True
        with th.no_grad():
            actions, _, _ = policy(obs, action_masks=masks)
        assert masks[np.arange(64), actions.numpy()].all()


def test_the_traced_rollout_forward_gives_sb3_contribs_actions_values_and_log_probs(env):
    """Without gradients the planner's forward runs traced: the same actions (the same random numbers
    drawn), values and log-probabilities as sb3-contrib's forward, to the bit, also after a training step
    changed the weights in place; with gradients it is sb3-contrib's own."""
    from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy

    th.manual_seed(0)
    policy = MotionPlannerPolicy(env.observation_space, env.action_space, lambda _: 1e-3, **TINY_POLICY)
    policy._heads.after_calls = 1  # the module for a shape's first call, traced from its second
    rng = np.random.default_rng(0)
    for batch, update in ((2, False), (2, True), (5, False)):
        obs = obs_as_tensor(observations(env, batch, seed=batch), "cpu")
        if update:
            loss = policy.evaluate_actions(obs, th.zeros(batch))[0].mean()
            policy.optimizer.zero_grad()
            loss.backward()
            policy.optimizer.step()
        masks = rng.random((batch, 6)) < 0.5
        masks[:, 0] = True
        for given, deterministic in ((masks, False), (None, False), (masks, True)):
            outputs = []
            for forward in (policy.forward, partial(MaskableActorCriticPolicy.forward, policy)):
                th.manual_seed(1)
                with th.no_grad():
                    outputs.append(forward(obs, deterministic=deterministic, action_masks=given))
            for traced, reference in zip(*outputs, strict=True):
                assert th.equal(traced, reference)
    assert len(policy._heads._traced) == 2  # batches of 2 and of 5
    obs = obs_as_tensor(observations(env, 2), "cpu")
    th.manual_seed(1)
    _, _, log_prob = policy(obs)
    assert log_prob.requires_grad  # with gradients, sb3-contrib's forward
    unshared = MotionPlannerPolicy(
        env.observation_space, env.action_space, lambda _: 1e-3, share_features_extractor=False, **TINY_POLICY
    )
    unshared._heads.after_calls = 0
    with th.no_grad():
        actions, _, _ = unshared(obs)
    assert actions.shape == (2,)
    assert not unshared._heads._calls and not unshared._heads._traced  # its own extractors: sb3-contrib's


def test_saved_model_loads_and_predicts_with_masks_in_a_fresh_process(env, tmp_path):
    model = MaskablePPO(
        MotionPlannerPolicy, env, policy_kwargs=TINY_POLICY, n_steps=16, batch_size=16, seed=0
    )
    model.save(tmp_path / "planner.zip")
    obs = observations(env, 4)
    masks = np.zeros((4, 6), dtype=bool)
    masks[:, 3] = True  # only "slowly turn right" allowed
    logits_mask = np.array([[True, False, True, False, True, True]] * 4)
    expected, _ = model.predict(obs, action_masks=logits_mask, deterministic=True)
    np.savez(tmp_path / "obs.npz", masks=masks, logits_mask=logits_mask, **obs)
    code = (
        "import sys, numpy as np, sb3_gccp\n"
        "from sb3_contrib import MaskablePPO\n"
        "data = dict(np.load(sys.argv[1] + '/obs.npz'))\n"
        "masks, logits_mask = data.pop('masks'), data.pop('logits_mask')\n"
        "model = MaskablePPO.load(sys.argv[1] + '/planner.zip')\n"
        "only, _ = model.predict(data, action_masks=masks)\n"
        "best, _ = model.predict(data, action_masks=logits_mask, deterministic=True)\n"
        "print(type(model.policy).__module__, only.tolist(), best.tolist())\n"
    )
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split(maxsplit=1) == ["sb3_gccp.policies", f"[3, 3, 3, 3] {expected.tolist()}\n"]


def test_tiny_maskable_ppo_run_trains_every_part_of_the_policy():
    env = gym.make("GCCPPlanner-v0", **WORLD)
    model = MaskablePPO(
        MotionPlannerPolicy, env, policy_kwargs=TINY_POLICY, n_steps=16, batch_size=16, n_epochs=2, seed=0
    )
    policy = model.policy
    parts = {
        **dict(policy.features_extractor.encoder.named_children()),
        "policy head": nn.Sequential(policy.mlp_extractor.policy_net, policy.action_net),
        "value head": nn.Sequential(policy.mlp_extractor.value_net, policy.value_net),
    }
    before = {name: [p.detach().clone() for p in part.parameters()] for name, part in parts.items()}
    model.learn(32)
    assert model.num_timesteps == 32
    # Compared part by part: without traffic, attention queries over a single key get no gradient.
    unchanged = [
        name
        for name, part in parts.items()
        if all(th.equal(p, q) for p, q in zip(part.parameters(), before[name], strict=True))
    ]
    assert unchanged == []
