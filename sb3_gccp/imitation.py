"""Imitation pre-training of the motion-planner: behaviour cloning of the scripted planner.

PPO on ``GCCPPlanner-v0`` learns to drive to subgoals but never to brake for one it should stop on
(README): braking is a long chain of one action whose pay-off comes at the end. The scripted
pure-pursuit planner (:class:`gccp_envs.scripted.ScriptedPlanner`) does stop. This module drives it
on the planner env, records (observation, action mask, action) and fits a MaskablePPO policy to it by
maximum likelihood under the same masks, so that a learned ``MotionPlannerPolicy`` starts from (or
stays at) a planner that stops. The planner stage runs it before PPO when the zoo entry has an
``imitation`` map (see :class:`ImitationSettings`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch as th
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig, reject_unknown_keys, require_int, require_positive
from gccp_envs.planner_env import GCCPPlannerEnv
from gccp_envs.scripted import ScriptedPlanner, SearchPlanner
from sb3_gccp.progress import new_bar

EXPERTS = {"scripted": ScriptedPlanner, "search": SearchPlanner}
"""The planners the planner stage can clone, by the name the ``imitation.expert`` key takes."""


@dataclass(frozen=True)
class ImitationSettings:
    """The ``imitation`` map of a planner entry (ours; the paper trains the planner by PPO only)."""

    expert: str = "scripted"
    """The planner to clone: 'scripted' (pure pursuit, :class:`ScriptedPlanner`) or 'search' (earliest
    arrival over an action-sequence library, :class:`SearchPlanner`)."""
    expert_steps: int = 40_000
    """Planner-env steps the expert drives to make the data set (one env, seeded episodes)."""
    epochs: int = 4
    """Passes over the data set."""
    batch_size: int = 256
    """Transitions per gradient step."""
    learning_rate: float = 3e-4
    """Adam's learning rate of the cloning (PPO's optimiser is not touched)."""

    def __post_init__(self) -> None:
        if self.expert not in EXPERTS:
            raise ValueError(f"imitation.expert must be one of {', '.join(EXPERTS)}, got {self.expert!r}")
        for name in ("expert_steps", "epochs", "batch_size"):
            require_int(f"imitation.{name}", getattr(self, name))
        require_positive("imitation.learning_rate", self.learning_rate)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> ImitationSettings:
        """Settings from a YAML map, rejecting unknown keys by name."""
        if not isinstance(values, Mapping):
            raise ValueError(
                f"imitation must be a map of {', '.join(cls.__dataclass_fields__)}, got {values!r}"
            )
        reject_unknown_keys(values, cls, "imitation")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Plain data."""
        return asdict(self)


@dataclass
class ExpertData:
    """Transitions of the scripted planner: observations (one array per key), masks and actions."""

    obs: dict[str, np.ndarray]
    masks: np.ndarray
    actions: np.ndarray
    episodes: int


def collect_expert(
    world: IntersectionConfig, steps: int, seed: int, progress: bool = False, expert: str = "scripted"
) -> ExpertData:
    """Drive an expert planner on ``GCCPPlanner-v0`` for ``steps`` steps (episodes seeded from
    ``seed`` on).

    :param expert: a key of ``EXPERTS``
    :return: the transitions
    """
    env = GCCPPlannerEnv(world)
    driver = EXPERTS[expert](env.config)
    records: list[dict[str, np.ndarray]] = []
    masks, actions = [], []
    episode = 0
    obs, _ = env.reset(seed=seed)
    with new_bar(total=steps, enabled=progress, desc="expert steps") as bar:
        for _ in range(steps):
            mask = env.action_masks()
            action = driver(obs, mask)
            records.append(obs)
            masks.append(mask)
            actions.append(action)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                episode += 1
                obs, _ = env.reset(seed=seed + episode)
            bar.update()
    env.close()
    stacked = {key: np.stack([r[key] for r in records]) for key in records[0]}
    return ExpertData(stacked, np.stack(masks), np.asarray(actions, np.int64), episode)


def clone(
    model: MaskablePPO, data: ExpertData, settings: ImitationSettings, seed: int, progress: bool = False
) -> list[dict[str, float]]:
    """Fit the model's policy to the expert's actions (masked log-likelihood); the value head is left
    as it is.

    :return: per epoch, the mean negative log-likelihood and the share of actions the policy's most
        likely action matches
    """
    policy = model.policy
    optimizer = th.optim.Adam(policy.parameters(), lr=settings.learning_rate)
    rng = np.random.default_rng(seed)
    n = len(data.actions)
    history = []
    policy.set_training_mode(True)
    with new_bar(total=settings.epochs * n, enabled=progress, desc="cloning") as bar:
        for _ in range(settings.epochs):
            order = rng.permutation(n)
            nll = matched = 0.0
            for start in range(0, n, settings.batch_size):
                rows = order[start : start + settings.batch_size]
                obs = {
                    key: th.as_tensor(value[rows], device=policy.device) for key, value in data.obs.items()
                }
                actions = th.as_tensor(data.actions[rows], device=policy.device)
                distribution = policy.get_distribution(obs, action_masks=data.masks[rows])
                loss = -distribution.log_prob(actions).mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                nll += float(loss.detach()) * len(rows)
                matched += float((distribution.mode() == actions).sum())
                bar.update(len(rows))
            history.append({"nll": nll / n, "accuracy": matched / n})
    policy.set_training_mode(False)
    return history
