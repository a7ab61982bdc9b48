"""The scene encoder: shapes, padding that never leaks, no NaN, gradients, goals, batch independence."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F

from sb3_gccp.networks import AttentionPool, EncoderConfig, MaskedAttention, SceneEncoder

TINY = EncoderConfig(hidden_size=16, num_heads=2, token_size=8, token_heads=2, bev_channels=(4, 4))
V, T_H, N_R, N_P = 6, 10, 3, 50
PRESENT = (0, 1, 2, 3)
"""Present vehicles of the synthetic scenes: vehicle 3 has no route, vehicles 4 and 5 are absent."""


def synthetic_obs(batch: int = 3, seed: int = 0) -> dict[str, th.Tensor]:
    """Random scenes with padded history steps, padded route tails, a vehicle without routes and two
    absent vehicles; padded entries hold random values too (the observation zero-pads them, but
    nothing may depend on them)."""
    gen = th.Generator().manual_seed(seed)
    history_mask = th.zeros(batch, V, T_H)
    routes_mask = th.zeros(batch, V, N_R, N_P)
    for b in range(batch):
        for i in PRESENT:
            seen = int(th.randint(1, T_H + 1, (1,), generator=gen))
            history_mask[b, i, T_H - seen :] = 1
        for i in (0, 1, 2):
            for j in range(int(th.randint(1, N_R + 1, (1,), generator=gen))):
                routes_mask[b, i, j, : int(th.randint(1, N_P + 1, (1,), generator=gen))] = 1
    return {
        "history": th.randn(batch, V, T_H, 9, generator=gen) * 10,
        "history_mask": history_mask,
        "routes": th.randn(batch, V, N_R, N_P, 8, generator=gen) * 10,
        "routes_mask": routes_mask,
        "bev": (th.rand(batch, 1, 64, 64, generator=gen) > 0.5).float(),
        "goal": th.randn(batch, 3, generator=gen) * 5,
    }


def perturb_padding(obs: dict[str, th.Tensor], seed: int = 1) -> dict[str, th.Tensor]:
    """A copy with fresh noise wherever a history or route vector is padded."""
    gen = th.Generator().manual_seed(seed)
    out = dict(obs)
    for key in ("history", "routes"):
        padded = obs[f"{key}_mask"][..., None] == 0
        noise = th.randn(obs[key].shape, generator=gen) * 100
        out[key] = th.where(padded, noise, obs[key])
    return out


def features(encoder: SceneEncoder, obs: dict[str, th.Tensor]) -> th.Tensor:
    """(B, 1, V, 5L) features of every vehicle with the observation's goal."""
    return encoder(obs, obs["goal"][:, None])


@pytest.fixture
def encoder() -> SceneEncoder:
    th.manual_seed(0)
    return SceneEncoder(TINY)


def test_shapes(encoder):
    obs = synthetic_obs(batch=3)
    scene = encoder.encode(obs)
    assert scene.history.shape == scene.interaction.shape == scene.route.shape == (3, V, 16)
    assert scene.drivable.shape == (3, 16)
    assert scene.present.tolist() == [[True] * 4 + [False] * 2] * 3
    goals = th.randn(3, 12, 3)
    goal_features = encoder.goal_features(goals)
    assert goal_features.shape == (3, 12, 16)
    assert encoder.vehicle_features(scene, goal_features).shape == (3, 12, V, 80)
    assert encoder.ego_features(scene, goal_features[:, 0]).shape == (3, 80)
    assert encoder.vehicle_feature_size == 80


def test_ego_features_are_vehicle_zero_of_vehicle_features(encoder):
    obs = synthetic_obs()
    scene = encoder.encode(obs)
    goal_features = encoder.goal_features(th.randn(3, 4, 3))
    every = encoder.vehicle_features(scene, goal_features)
    for g in range(4):
        th.testing.assert_close(every[:, g, 0], encoder.ego_features(scene, goal_features[:, g]))


@pytest.mark.parametrize("route_self_attention", [False, True])
def test_padded_values_do_not_change_any_feature(route_self_attention):
    th.manual_seed(0)
    encoder = SceneEncoder(replace(TINY, route_self_attention=route_self_attention))
    obs = synthetic_obs()
    noisy = perturb_padding(obs)
    assert not th.equal(noisy["routes"], obs["routes"])
    th.testing.assert_close(features(encoder, noisy), features(encoder, obs), rtol=0, atol=1e-6)


def test_absent_vehicles_and_missing_routes_give_zero_features(encoder):
    scene = encoder.encode(synthetic_obs())
    for name in ("history", "interaction", "route"):
        assert th.all(getattr(scene, name)[:, 4:] == 0), name
    assert th.all(scene.route[:, 3] == 0)  # present, but without any route
    assert th.all(scene.route[:, :3].abs().sum(-1) > 0)


def test_present_neighbours_matter_through_interaction(encoder):
    obs = synthetic_obs()
    changed = dict(obs, history=obs["history"].clone())
    changed["history"][:, 1] += 5.0  # a present neighbour moves
    before, after = encoder.encode(obs), encoder.encode(changed)
    th.testing.assert_close(after.history[:, 0], before.history[:, 0])
    assert not th.allclose(after.interaction[:, 0], before.interaction[:, 0])


def test_routes_matter_through_route_attention(encoder):
    obs = synthetic_obs()
    changed = dict(obs, routes=obs["routes"].clone())
    changed["routes"][:, 0, 0] += 5.0  # the ego's first route (always real)
    before, after = encoder.encode(obs), encoder.encode(changed)
    th.testing.assert_close(after.interaction, before.interaction)
    assert not th.allclose(after.route[:, 0], before.route[:, 0])
    th.testing.assert_close(after.route[:, 1:], before.route[:, 1:])


@pytest.mark.parametrize("present", [(0,), ()], ids=["ego-only", "empty"])
def test_no_nan_in_values_or_gradients_when_everything_else_is_padded(present):
    th.manual_seed(0)
    encoder = SceneEncoder(replace(TINY, route_self_attention=True))
    obs = synthetic_obs(batch=2)
    keep = th.zeros(V, dtype=th.bool)
    keep[list(present)] = True
    obs["history_mask"] = obs["history_mask"] * keep[:, None]
    obs["routes_mask"] = obs["routes_mask"] * keep[:, None, None]
    out = features(encoder, obs)
    out.sum().backward()
    assert th.isfinite(out).all()
    assert all(th.isfinite(p.grad).all() for p in encoder.parameters() if p.grad is not None)
    absent = [i for i in range(V) if i not in present]
    assert th.all(out[:, :, absent, : 3 * TINY.hidden_size] == 0)


@pytest.mark.parametrize("route_self_attention", [False, True])
def test_gradients_reach_every_parameter(route_self_attention):
    th.manual_seed(0)
    encoder = SceneEncoder(replace(TINY, route_self_attention=route_self_attention))
    obs = synthetic_obs(batch=4)
    (features(encoder, obs) ** 2).sum().backward()
    missing = [name for name, p in encoder.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert missing == []


def test_goal_changes_only_the_goal_feature(encoder):
    obs = synthetic_obs()
    scene = encoder.encode(obs)
    out = encoder.vehicle_features(
        scene, encoder.goal_features(th.tensor([[[5.0, 0, 0], [10.0, -3.0, -0.5]]] * 3))
    )
    hidden = TINY.hidden_size
    th.testing.assert_close(out[:, 0, :, : 4 * hidden], out[:, 1, :, : 4 * hidden])
    assert not th.allclose(out[:, 0, :, 4 * hidden :], out[:, 1, :, 4 * hidden :])


def test_each_scene_of_a_batch_is_encoded_independently(encoder):
    obs = synthetic_obs(batch=3)
    batched = features(encoder, obs)
    for b in range(3):
        single = features(encoder, {key: value[b : b + 1] for key, value in obs.items()})
        th.testing.assert_close(batched[b : b + 1], single, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("num_queries", [1, 4])
def test_masked_attention_matches_reference_attention(num_queries):
    th.manual_seed(0)
    attention = MaskedAttention(query_size=6, key_size=5, embed_size=8, num_heads=2)
    queries, keys = th.randn(7, num_queries, 6), th.randn(7, 3, 5)
    mask = th.rand(7, 3) > 0.4
    mask[:, 0] = True
    key, value = attention.key_value(keys).split(8, -1)

    def heads(x: th.Tensor) -> th.Tensor:
        return x.view(7, x.shape[1], 2, 4).transpose(1, 2)

    expected = F.scaled_dot_product_attention(
        heads(attention.query(queries)), heads(key), heads(value), attn_mask=mask[:, None, None, :]
    )
    expected = attention.out(expected.transpose(1, 2).reshape(7, num_queries, 8))
    th.testing.assert_close(attention(queries, keys, mask), expected, rtol=1e-5, atol=1e-6)


def test_attention_pool_ignores_masked_tokens_and_token_order():
    th.manual_seed(0)
    pool = AttentionPool(size=8, num_heads=2)
    tokens, mask = th.randn(4, 6, 8), th.rand(4, 6) > 0.5
    mask[:, 0] = True
    noisy = th.where(mask[..., None], tokens, th.randn(4, 6, 8) * 100)
    order = th.randperm(6)
    th.testing.assert_close(pool(noisy, mask), pool(tokens, mask), rtol=0, atol=1e-6)
    th.testing.assert_close(pool(tokens[:, order], mask[:, order]), pool(tokens, mask))


def test_real_observations_encode_to_finite_features():
    env = gym.make("GCCPPlanner-v0", spawn_probability=0.3, warmup_time=20.0)
    obs, _ = env.reset(seed=3)
    batch = []
    for _ in range(8):
        obs, *_ = env.step(1)
        batch.append(obs)
    tensors = {key: th.as_tensor(np.stack([o[key] for o in batch])).float() for key in batch[0]}
    assert tensors["history_mask"][:, 1:].any(), "the scene should have neighbours"
    out = features(SceneEncoder(), tensors)
    assert out.shape == (8, 1, V, 5 * EncoderConfig().hidden_size)
    assert th.isfinite(out).all()


def test_encoder_config_from_dict_rejects_unknown_keys_and_bad_sizes():
    assert EncoderConfig.from_dict({"bev_channels": [4, 8]}).bev_channels == (4, 8)
    assert EncoderConfig.from_dict(None) == EncoderConfig()
    with pytest.raises(ValueError, match="'hiden_size' \\(did you mean 'hidden_size'\\?\\)"):
        EncoderConfig.from_dict({"hiden_size": 64})
    with pytest.raises(ValueError, match="multiple of num_heads"):
        EncoderConfig(hidden_size=10, num_heads=4)
    with pytest.raises(ValueError, match="route_patch must be a positive integer"):
        EncoderConfig(route_patch=0)


def test_scene_encoder_rejects_other_vector_layouts():
    with pytest.raises(ValueError, match="expected 9 history and 8 route features"):
        SceneEncoder(TINY, history_features=7)
