"""Imitation pre-training of the motion-planner: behaviour cloning (and DAgger) of a scripted planner.

PPO on ``GCCPPlanner-v0`` learns to drive to subgoals but never to brake for one it should stop on
(README): braking is a long chain of one action whose pay-off comes at the end. The scripted
pure-pursuit planner (:class:`gccp_envs.scripted.ScriptedPlanner`) does stop. This module drives it
on the planner env, records (observation, action mask, action) and fits a MaskablePPO policy to it by
maximum likelihood under the same masks, so that a learned ``MotionPlannerPolicy`` starts from (or
stays at) a planner that stops. The expert is the pure-pursuit planner or the search planner
(:class:`gccp_envs.scripted.SearchPlanner`, which reaches more subgoals); DAgger rounds then let the
cloned policy drive and the expert label where it went. The planner stage runs it before PPO when the
zoo entry has an ``imitation`` map (see :class:`ImitationSettings`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
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
DAGGER_SEED_STRIDE = 1_000_000
"""Offset between the episode seeds of consecutive DAgger rounds."""


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
    dagger_rounds: int = 0
    """Rounds of DAgger (Ross et al. 2011) after the first fit: the cloned policy drives, the expert
    labels every state it visits, the labelled steps join the data set and the policy is fitted again
    (``epochs`` passes), so that it learns to recover from its own mistakes. 0: behaviour cloning only."""
    dagger_steps: int = 20_000
    """Planner-env steps the cloned policy drives in each DAgger round."""

    def __post_init__(self) -> None:
        if self.expert not in EXPERTS:
            raise ValueError(f"imitation.expert must be one of {', '.join(EXPERTS)}, got {self.expert!r}")
        for name in ("expert_steps", "epochs", "batch_size", "dagger_steps"):
            require_int(f"imitation.{name}", getattr(self, name))
        require_int("imitation.dagger_rounds", self.dagger_rounds, minimum=0)
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
    """Steps labelled by the expert: observations (one array per key), masks and the expert's actions."""

    obs: dict[str, np.ndarray]
    masks: np.ndarray
    actions: np.ndarray
    episodes: int
    agreement: float = 1.0
    """Share of the steps where the driver took the expert's action (1 when the expert drives)."""

    def __add__(self, other: ExpertData) -> ExpertData:
        """Both data sets in one (DAgger's aggregation)."""
        return ExpertData(
            {key: np.concatenate((value, other.obs[key])) for key, value in self.obs.items()},
            np.concatenate((self.masks, other.masks)),
            np.concatenate((self.actions, other.actions)),
            self.episodes + other.episodes,
            (self.agreement * len(self.actions) + other.agreement * len(other.actions))
            / (len(self.actions) + len(other.actions)),
        )


Driver = Callable[[dict[str, np.ndarray], np.ndarray], int]
"""A planner as a function of (observation, action mask) to an action."""


def policy_driver(model: MaskablePPO) -> Driver:
    """The model's most likely action under the mask (how the frozen planner drives)."""

    def drive(obs: dict[str, np.ndarray], mask: np.ndarray) -> int:
        action, _ = model.predict(obs, action_masks=mask, deterministic=True)
        return int(action)

    return drive


def collect_expert(
    world: IntersectionConfig,
    steps: int,
    seed: int,
    progress: bool = False,
    expert: str = "scripted",
    driver: Driver | None = None,
) -> ExpertData:
    """Label ``steps`` steps of ``GCCPPlanner-v0`` (episodes seeded from ``seed`` on) with an expert
    planner's actions.

    :param expert: a key of ``EXPERTS``
    :param driver: who drives (DAgger: the cloned policy); default the expert itself
    :return: the states visited, with the expert's actions
    """
    env = GCCPPlannerEnv(world)
    label = EXPERTS[expert](env.config)
    records: list[dict[str, np.ndarray]] = []
    masks, actions = [], []
    episode = agreed = 0
    obs, _ = env.reset(seed=seed)
    with new_bar(
        total=steps, enabled=progress, desc="expert steps" if driver is None else "DAgger steps"
    ) as bar:
        for _ in range(steps):
            mask = env.action_masks()
            action = label(obs, mask)
            records.append(obs)
            masks.append(mask)
            actions.append(action)
            if driver is not None:
                driven = driver(obs, mask)
                agreed += driven == action
                action = driven
            else:
                agreed += 1
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                episode += 1
                obs, _ = env.reset(seed=seed + episode)
            bar.update()
    env.close()
    stacked = {key: np.stack([r[key] for r in records]) for key in records[0]}
    return ExpertData(stacked, np.stack(masks), np.asarray(actions, np.int64), episode, agreed / steps)


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


def imitate(
    model: MaskablePPO,
    world: IntersectionConfig,
    settings: ImitationSettings,
    seed: int,
    progress: bool = False,
) -> dict[str, Any]:
    """Clone the expert into ``model``'s policy, then run the DAgger rounds.

    Round k's episodes are seeded from ``seed + k * DAGGER_SEED_STRIDE``, apart from the expert's.

    :return: the record written to ``imitation.json``: the settings, the expert's episodes, the first
        fit per epoch and, per DAgger round, the episodes driven, the share of the visited steps where
        the policy already chose the expert's action, the data set's size and the fit per epoch
    """
    data = collect_expert(world, settings.expert_steps, seed, progress, settings.expert)
    record: dict[str, Any] = {
        "settings": settings.to_dict(),
        "expert_episodes": data.episodes,
        "epochs": clone(model, data, settings, seed, progress),
        "dagger": [],
    }
    for k in range(1, settings.dagger_rounds + 1):
        visited = collect_expert(
            world,
            settings.dagger_steps,
            seed + k * DAGGER_SEED_STRIDE,
            progress,
            settings.expert,
            driver=policy_driver(model),
        )
        data = data + visited
        record["dagger"].append(
            {
                "episodes": visited.episodes,
                "policy_agreed": visited.agreement,
                "data_steps": len(data.actions),
                "epochs": clone(model, data, settings, seed + k, progress),
            }
        )
    return record
