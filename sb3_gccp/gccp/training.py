"""Training and evaluation of the goal-conditioned trajectory predictor (paper III-E, Eq. 2, Algorithm 1).

At the end of every episode the predictor takes K_p Adam steps, each on N_b decision points drawn
from the replay buffer, minimising the smooth-L1 error of the predicted futures of the ego and of the
neighbours (Eq. 2). A vehicle enters the loss at the future steps it exists in the simulation and
only if the observation shows it (a vehicle without any history vector cannot be located): padded
neighbour rows and steps after the episode ended count for nothing.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch as th
import torch.nn.functional as F
from torch import nn

from sb3_gccp.gccp.replay import EpisodeReplayBuffer, to_torch


def prediction_loss(pred: th.Tensor, target: th.Tensor, present: th.Tensor) -> th.Tensor:
    """Eq. 2: smooth-L1 error of the predicted futures of the ego and the neighbours.

    The heading error is wrapped to (-pi, pi] first; the smooth-L1 terms of x, y and heading are
    averaged over the present (scene, vehicle, step) entries, which is Eq. 2's average over the batch
    and the N_s + 1 vehicles when every entry is present.

    :param pred: (B, V, T_f, 3) predicted poses (x, y, heading)
    :param target: (B, V, T_f, 3) ground-truth poses
    :param present: (B, V, T_f) bool or 0/1, the entries that count
    :return: the scalar loss (0 when nothing is present)
    """
    error = pred - target
    heading = th.atan2(th.sin(error[..., 2]), th.cos(error[..., 2]))
    error = th.cat((error[..., :2], heading[..., None]), -1)
    terms = F.smooth_l1_loss(error, th.zeros_like(error), reduction="none").sum(-1)
    weight = present.to(terms.dtype)
    return (terms * weight).sum() / (3 * weight.sum()).clamp_min(1.0)


def loss_mask(batch: Mapping[str, th.Tensor]) -> th.Tensor:
    """The entries of a batch that count: future steps that exist of vehicles the observation shows.

    :param batch: ``history_mask`` (B, V, T_h) and ``future_mask`` (B, V, T_f)
    :return: (B, V, T_f) bool
    """
    seen = (batch["history_mask"] > 0).any(-1, keepdim=True)
    return batch["future_mask"].bool() & seen


class PredictorTrainer:
    """Trains a trajectory predictor from an :class:`~sb3_gccp.gccp.replay.EpisodeReplayBuffer` (Algorithm 1).

    :param predictor: a :class:`~sb3_gccp.gccp.predictor.TrajectoryPredictor`
    :param learning_rate: Adam's learning rate (paper: fixed 1e-4)
    :param batch_size: N_b, decisions per gradient step (paper: 64)
    :param steps_per_episode: K_p, gradient steps at the end of each episode (paper: 5)
    :param device: where the predictor lives
    """

    def __init__(
        self,
        predictor: nn.Module,
        learning_rate: float = 1e-4,
        batch_size: int = 64,
        steps_per_episode: int = 5,
        device: str | th.device = "cpu",
    ) -> None:
        self.predictor = predictor.to(device)
        self.optimizer = th.optim.Adam(predictor.parameters(), lr=learning_rate)
        self.batch_size = batch_size
        self.steps_per_episode = steps_per_episode
        self.device = device
        self.gradient_steps = 0

    def train_steps(self, buffer: EpisodeReplayBuffer, n_steps: int, rng: np.random.Generator) -> float:
        """Take ``n_steps`` gradient steps on uniform batches of the replay buffer.

        :param buffer: the replay buffer D (not empty)
        :param n_steps: gradient steps
        :param rng: draws the batches
        :return: the mean loss over the steps (nan for no step)
        """
        self.predictor.train()
        losses = []
        for _ in range(n_steps):
            batch = to_torch(buffer.sample(self.batch_size, rng), self.device)
            pred = self.predictor(batch, batch["subgoal"][:, None])[:, 0]
            loss = prediction_loss(pred, batch["future"], loss_mask(batch))
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            losses.append(loss.item())
        self.gradient_steps += n_steps
        return float(np.mean(losses)) if losses else float("nan")


def displacement_errors(
    predictor: nn.Module,
    data: EpisodeReplayBuffer | Mapping[str, np.ndarray],
    batch_size: int = 256,
    device: str | th.device = "cpu",
) -> dict[str, float]:
    """Average and final displacement errors [m] of the predicted positions over T_f steps (1 s).

    ADE averages the position error over the entries that count (see :func:`loss_mask`); FDE over the
    vehicles whose last step T_f counts. Each is given over the ego and the neighbours together
    (``ade``, ``fde``), over the ego (``ego_ade``, ``ego_fde``) and over the neighbours
    (``neighbour_ade``, ``neighbour_fde``); nan where nothing counts.

    :param predictor: any predictor with the call signature of
        :class:`~sb3_gccp.gccp.predictor.TrajectoryPredictor` (learned, no-goal or constant velocity)
    :param data: a replay buffer or arrays in its layout (state keys, ``subgoal``, ``future``,
        ``future_mask``)
    :param batch_size: decisions per forward pass
    :param device: where the predictor lives
    :return: the six errors
    """
    arrays = data.stored() if isinstance(data, EpisodeReplayBuffer) else data
    count = len(arrays["future"])
    errors, masks = [], []
    predictor.eval()
    with th.inference_mode():
        for start in range(0, count, batch_size):
            batch = to_torch(
                {key: value[start : start + batch_size] for key, value in arrays.items()}, device
            )
            pred = predictor(batch, batch["subgoal"][:, None])[:, 0]
            errors.append(th.linalg.vector_norm(pred[..., :2] - batch["future"][..., :2], dim=-1).cpu())
            masks.append(loss_mask(batch).cpu())
    error, mask = th.cat(errors), th.cat(masks)  # (N, V, T_f)
    result = {}
    for name, rows in (("", slice(None)), ("ego_", slice(0, 1)), ("neighbour_", slice(1, None))):
        result[f"{name}ade"] = _masked_mean(error[:, rows], mask[:, rows])
        result[f"{name}fde"] = _masked_mean(error[:, rows, -1], mask[:, rows, -1])
    return result


def _masked_mean(values: th.Tensor, mask: th.Tensor) -> float:
    """Mean of ``values`` where ``mask`` is True; nan if it is nowhere."""
    return float(values[mask].mean()) if mask.any() else float("nan")
