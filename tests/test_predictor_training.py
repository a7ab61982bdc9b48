"""Eq. 2's loss, the predictor trainer (K_p steps per episode) and ADE/FDE for every predictor kind."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from helpers import TINY_ENCODER as TINY

from sb3_gccp.gccp.predictor import ConstantVelocityPredictor, PredictorConfig, TrajectoryPredictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer, collect_decisions, to_torch
from sb3_gccp.gccp.training import PredictorTrainer, displacement_errors, loss_mask, prediction_loss


@pytest.fixture(scope="module")
def buffer() -> EpisodeReplayBuffer:
    """A few dozen real decision points with traffic."""
    env = gym.make("GCCPDecider-v0", spawn_probability=0.3, duration=8.0)
    rng = np.random.default_rng(1)
    replay = EpisodeReplayBuffer(capacity=100)
    collect_decisions(env, lambda obs, mask: int(rng.integers(12)), 6, replay, rng)
    return replay


def tiny_predictor(goal_condition: bool = True) -> TrajectoryPredictor:
    th.manual_seed(0)
    return TrajectoryPredictor(
        PredictorConfig(encoder=TINY, decoder_hidden=32, goal_condition=goal_condition)
    )


def test_loss_is_smooth_l1_when_everything_is_present():
    gen = th.Generator().manual_seed(0)
    pred, target = th.randn(4, 6, 10, 3, generator=gen) * 3, th.randn(4, 6, 10, 3, generator=gen) * 3
    target[..., 2] = target[..., 2].clamp(-1, 1)
    pred[..., 2] = pred[..., 2].clamp(-1, 1)
    th.testing.assert_close(
        prediction_loss(pred, target, th.ones(4, 6, 10, dtype=th.bool)), F.smooth_l1_loss(pred, target)
    )


def test_loss_ignores_absent_entries():
    gen = th.Generator().manual_seed(0)
    pred = th.randn(2, 6, 10, 3, generator=gen).clamp(-1, 1).requires_grad_()
    target = th.randn(2, 6, 10, 3, generator=gen).clamp(-1, 1)
    present = th.zeros(2, 6, 10, dtype=th.bool)
    present[:, :3] = True
    present[1, 2, 6:] = False  # a vehicle whose episode ended
    changed = th.where(present[..., None], target, th.randn(2, 6, 10, 3, generator=gen) * 100)
    loss = prediction_loss(pred, target, present)
    th.testing.assert_close(prediction_loss(pred, changed, present), loss)
    th.testing.assert_close(loss, F.smooth_l1_loss(pred[present], target[present]))
    loss.backward()
    assert pred.grad is not None and th.all(pred.grad[~present] == 0)


def test_loss_wraps_heading_errors():
    pred, target = th.zeros(1, 1, 1, 3), th.zeros(1, 1, 1, 3)
    pred[..., 2], target[..., 2] = np.pi - 0.05, -np.pi + 0.05
    small = th.zeros(1, 1, 1, 3)
    small[..., 2] = 0.1
    present = th.ones(1, 1, 1, dtype=th.bool)
    th.testing.assert_close(
        prediction_loss(pred, target, present), prediction_loss(small, th.zeros_like(small), present)
    )


def test_loss_of_nothing_is_zero_with_finite_gradients():
    pred = th.randn(2, 6, 10, 3, requires_grad=True)
    loss = prediction_loss(pred, th.zeros(2, 6, 10, 3), th.zeros(2, 6, 10, dtype=th.bool))
    loss.backward()
    assert loss.item() == 0.0 and pred.grad is not None and th.isfinite(pred.grad).all()


def test_loss_mask_needs_a_history_and_a_future():
    batch = {"history_mask": th.zeros(1, 3, 10), "future_mask": th.ones(1, 3, 10, dtype=th.bool)}
    batch["history_mask"][0, :2, -1] = 1.0
    batch["future_mask"][0, 1, 5:] = False
    expected = th.zeros(1, 3, 10, dtype=th.bool)
    expected[0, 0] = True
    expected[0, 1, :5] = True
    th.testing.assert_close(loss_mask(batch), expected)


def test_predictor_overfits_a_tiny_buffer(buffer):
    tiny = EpisodeReplayBuffer(capacity=16)
    data = buffer.stored()
    for i in range(16):
        tiny.add(
            {key: data[key][i] for key in ("history", "history_mask", "routes", "routes_mask", "bev")},
            data["subgoal"][i],
            data["future"][i],
            data["future_mask"][i] > 0,
        )
    tiny.end_episode()
    trainer = PredictorTrainer(tiny_predictor(), learning_rate=3e-3, batch_size=16)
    rng = np.random.default_rng(0)
    first = trainer.train_steps(tiny, 10, rng)
    trainer.train_steps(tiny, 130, rng)
    last = trainer.train_steps(tiny, 10, rng)
    assert trainer.gradient_steps == 150
    assert last < 0.1 * first, (first, last)


def test_steps_taken_one_at_a_time_train_as_steps_taken_together(buffer):
    # The GCCP callback spreads an episode's K_p steps over the next env steps.
    together, apart = (PredictorTrainer(tiny_predictor(), batch_size=8) for _ in range(2))
    apart.predictor.load_state_dict(together.predictor.state_dict())
    before = [p.detach().clone() for p in together.predictor.parameters()]
    loss = together.train_steps(buffer, 3, np.random.default_rng(0))
    rng = np.random.default_rng(0)
    losses = [apart.train_steps(buffer, 1, rng) for _ in range(3)]
    assert loss == np.mean(losses) and together.gradient_steps == apart.gradient_steps == 3
    for a, b, c in zip(together.predictor.parameters(), apart.predictor.parameters(), before, strict=True):
        assert th.equal(a, b) and not th.equal(a, c)
    assert np.isnan(together.train_steps(buffer, 0, rng))


def test_displacement_errors_measure_position_errors(buffer):
    data = buffer.stored()
    batch = to_torch(data)
    with th.inference_mode():
        cv = ConstantVelocityPredictor()(batch, batch["subgoal"][:, None])[:, 0].numpy()
    exact = dict(data, future=cv.copy())
    errors = displacement_errors(ConstantVelocityPredictor(), exact, batch_size=7)
    assert set(errors) == {"ade", "fde", "ego_ade", "ego_fde", "neighbour_ade", "neighbour_fde"}
    assert max(errors.values()) < 1e-5
    shifted = cv.copy()
    shifted[:, 0, :, :2] += [0.6, 0.8]  # the ego's future 1 m off
    errors = displacement_errors(ConstantVelocityPredictor(), dict(data, future=shifted))
    assert errors["ego_ade"] == pytest.approx(1.0, abs=1e-5) and errors["ego_fde"] == pytest.approx(
        1.0, abs=1e-5
    )
    assert errors["neighbour_ade"] < 1e-5 and 0.0 < errors["ade"] < 1.0


@pytest.mark.parametrize("goal_condition", [True, False])
def test_displacement_errors_of_learned_predictors(buffer, goal_condition):
    errors = displacement_errors(tiny_predictor(goal_condition), buffer)
    assert all(np.isfinite(value) and value > 0 for value in errors.values())
