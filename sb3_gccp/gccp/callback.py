"""The GCCP callback: trains the predictor beside the decision-maker and hands masks to the envs.

Algorithm 1 of the paper, as an SB3 callback on MaskablePPO over ``GCCPDecider-v0``:

- every decision of every training env goes into that env's episode buffer D_e, from the raw features
  the env puts in ``info`` (``decision_obs``, ``subgoal``, ``future``, ``future_mask``), so that a
  ``VecNormalize`` wrapper would not matter;
- at an episode's end D_e moves into the replay buffer D and the predictor takes K_p gradient steps
  on batches of N_b decisions;
- from episode N_m on, every env worker masks subgoals with the GCCP module: the callback sends each
  worker a :class:`~sb3_gccp.prediction.GCCPMask` with a copy of the predictor through
  ``VecEnv.env_method("set_mask_fn", ...)`` (``set_attr`` would set the Monitor wrapper), again after
  every rollout so that the workers use the latest weights;
- training stops after N_e episodes.

It logs the predictor loss, ADE/FDE on the latest decisions, the share of masked candidates and the
success and collision rates to TensorBoard, keeps one row per episode for the training curve, and
saves everything needed to resume (model, predictor, optimiser, replay buffer, counters).
"""

from __future__ import annotations

import copy
import csv
from collections import deque
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from torch import nn
from tqdm.auto import tqdm

from gccp_envs.config import reject_unknown_keys, require_int, require_non_negative, require_positive
from sb3_gccp.collision import CollisionChecker
from sb3_gccp.prediction import (
    ConstantVelocityPredictor,
    GCCPMask,
    PredictorConfig,
    TrajectoryPredictor,
    load_predictor,
    save_predictor,
)
from sb3_gccp.predictor_training import PredictorTrainer, displacement_errors
from sb3_gccp.progress import new_bar
from sb3_gccp.replay import EpisodeReplayBuffer

PREDICTORS = ("learned", "no_goal", "cv", "none")
"""GCCP variants: the paper's learned predictor, and the ablations w/o goal condition, w/ CV, w/o GCCP."""
LEARNED = ("learned", "no_goal")
EPISODE_FIELDS = ("episode", "timesteps", "task", "success", "crashed", "offroad", "timeout", "masks_on")


@dataclass(frozen=True)
class GCCPSettings:
    """The ``gccp`` map of a decider's zoo config: the paper's schedule and the predictor's training."""

    n_episodes: int = 2000
    """N_e: decider training episodes (paper: 2000)."""
    mask_after_episodes: int = 800
    """N_m: episodes before the GCCP masks are switched on (paper: 800)."""
    planner_episodes: int | None = None
    """N_g: with ``train --stage all``, stop the planner stage after this many planner-env episodes
    (paper: 500); None trains it for its own ``n_timesteps``."""
    predictor: str = "learned"
    """learned (the paper), no_goal (w/o goal condition), cv (w/ CV) or none (w/o GCCP)."""
    predictor_kwargs: Mapping[str, Any] = field(default_factory=dict)
    """:class:`~sb3_gccp.prediction.PredictorConfig` fields (encoder sizes, decoder width)."""
    predictor_init: str | None = None
    """Start from these predictor weights (a ``predictor.pt``) instead of random ones."""
    predictor_learning_rate: float = 1e-4
    """Adam's learning rate of the predictor (paper: 1e-4)."""
    predictor_batch_size: int = 64
    """N_b: decisions per predictor gradient step (paper: 64)."""
    predictor_steps_per_episode: int = 5
    """K_p: predictor gradient steps per finished episode (paper: 5)."""
    buffer_capacity: int = 20_000
    """Decisions kept in the replay buffer D (paper: not given)."""
    save_every_episodes: int = 100
    """Episodes between checkpoints (model, predictor, optimiser, replay buffer)."""
    mask_margin: float = 0.0
    """Extra length and width [m] of every box in the collision check (paper: none)."""
    mask_extrapolate_steps: int = 0
    """Steps checked beyond the predicted T_f, every vehicle keeping its last predicted velocity
    (paper: 0, a 1 s check; see docs/design.md for why a longer one helps at our speeds)."""
    mask_ego_deceleration: float | None = None
    """In those extra steps the ego brakes to a stop at this deceleration [m/s^2]; null (the shipped
    mask): it goes on at its last predicted velocity like the neighbours. 4 was tried, not adopted."""
    mask_yield_margin: float | None = None
    """A neighbour that stands with the ego's box in its lane ahead waits for the ego: it is checked where
    it stands, with this box margin [m], instead of along its prediction; null: along its prediction
    (the paper). Breaks the stand-offs in which the ego blocks a car that the mask predicts to go."""

    def __post_init__(self) -> None:
        if self.predictor not in PREDICTORS:
            raise ValueError(f"gccp.predictor must be one of {', '.join(PREDICTORS)}, got {self.predictor!r}")
        for name in ("n_episodes", "predictor_batch_size", "buffer_capacity", "save_every_episodes"):
            require_int(f"gccp.{name}", getattr(self, name))
        require_non_negative("gccp.mask_margin", self.mask_margin)
        if self.mask_ego_deceleration is not None:
            require_positive("gccp.mask_ego_deceleration", self.mask_ego_deceleration)
        if self.mask_yield_margin is not None:
            require_non_negative("gccp.mask_yield_margin", self.mask_yield_margin)
        for name in ("mask_after_episodes", "predictor_steps_per_episode", "mask_extrapolate_steps"):
            require_int(f"gccp.{name}", getattr(self, name), minimum=0)
        if self.planner_episodes is not None and (
            not isinstance(self.planner_episodes, int) or self.planner_episodes < 1
        ):
            raise ValueError(
                f"gccp.planner_episodes must be a positive integer or null, got {self.planner_episodes!r}"
            )
        require_positive("gccp.predictor_learning_rate", self.predictor_learning_rate)
        PredictorConfig.from_dict(self.predictor_kwargs)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> GCCPSettings:
        """Settings from the ``gccp`` map, rejecting unknown keys by name."""
        values = dict(values or {})
        reject_unknown_keys(values, cls, "gccp settings")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Plain data for YAML."""
        values = asdict(self)
        values["predictor_kwargs"] = dict(self.predictor_kwargs)
        return values

    def make_mask(self, predictor: nn.Module) -> GCCPMask:
        """The GCCP mask function of these settings around ``predictor``."""
        return GCCPMask(
            predictor,
            CollisionChecker(margin=self.mask_margin),
            self.mask_extrapolate_steps,
            self.mask_ego_deceleration,
            self.mask_yield_margin,
        )

    def make_predictor(self) -> nn.Module | None:
        """A fresh predictor of this variant (``None`` without GCCP)."""
        if self.predictor == "none":
            return None
        if self.predictor == "cv":
            return ConstantVelocityPredictor()
        if self.predictor_init is not None:
            predictor = load_predictor(self.predictor_init)
            if predictor.config.goal_condition != (self.predictor == "learned"):
                raise ValueError(
                    f"gccp.predictor_init {self.predictor_init} is not a {self.predictor} predictor"
                )
            return predictor
        config = PredictorConfig.from_dict(
            {**self.predictor_kwargs, "goal_condition": self.predictor == "learned"}
        )
        return TrajectoryPredictor(config)


class GCCPCallback(BaseCallback):
    """Fills the replay buffer, trains the predictor, pushes GCCP masks, stops after N_e episodes.

    :param settings: schedule and predictor training
    :param predictor: the predictor (trained here if learned; ``None`` without GCCP)
    :param buffer: the replay buffer D
    :param seed: seeds the predictor's batch sampling
    :param progress_bar: show a progress bar over episodes
    """

    def __init__(
        self,
        settings: GCCPSettings,
        predictor: nn.Module | None,
        buffer: EpisodeReplayBuffer,
        seed: int = 0,
        progress_bar: bool = False,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.settings = settings
        self.predictor = predictor
        self.buffer = buffer
        self.trainer = (
            PredictorTrainer(
                predictor,
                learning_rate=settings.predictor_learning_rate,
                batch_size=settings.predictor_batch_size,
                steps_per_episode=settings.predictor_steps_per_episode,
            )
            if predictor is not None and settings.predictor in LEARNED
            else None
        )
        self.rng = np.random.default_rng(seed)
        self.progress_bar = progress_bar
        self.episodes = 0
        self.masks_on = False
        self.history: list[dict[str, Any]] = []
        self.checkpoint_dir: Path | None = None
        self._staged: list[list[tuple[Any, ...]]] = []
        self._losses: list[float] = []
        self._masked: list[float] = []
        self._recent: deque[dict[str, Any]] = deque(maxlen=100)
        self._bar: tqdm | None = None

    # --- SB3 hooks -----------------------------------------------------------------------------
    def _on_training_start(self) -> None:
        self._staged = [[] for _ in range(self.training_env.num_envs)]
        self._bar = new_bar(
            total=self.settings.n_episodes, initial=self.episodes, enabled=self.progress_bar, unit="ep"
        )
        if self.masks_on:  # resumed after N_m
            self.push_masks()

    def _on_step(self) -> bool:
        infos: list[dict[str, Any]] = self.locals["infos"]
        dones = self.locals["dones"]
        for i, (info, done) in enumerate(zip(infos, dones, strict=True)):
            if self.trainer is not None:
                self._staged[i].append(
                    (info["decision_obs"], info["subgoal"], info["future"], info["future_mask"])
                )
            self._masked.append(float(info.get("masked_share", 0.0)))
            if done:
                self._end_episode(i, info)
                if self.episodes >= self.settings.n_episodes:
                    return False
        return True

    def _on_rollout_end(self) -> None:
        if self.masks_on and self.trainer is not None:
            self.push_masks()
        log = self.logger.record
        log("gccp/episodes", self.episodes)
        log("gccp/masks_on", float(self.masks_on))
        if self._masked:
            log("gccp/masked_share", float(np.mean(self._masked)))
        if self._losses:
            log("gccp/predictor_loss", float(np.nanmean(self._losses)))
        if self.trainer is not None and len(self.buffer) and self.predictor is not None:
            errors = displacement_errors(self.predictor, self.buffer.latest(256))
            log("gccp/ade", errors["ade"])
            log("gccp/fde", errors["fde"])
        if self._recent:
            log("rollout/success_rate", float(np.mean([e["success"] for e in self._recent])))
            log("rollout/collision_rate", float(np.mean([e["crashed"] for e in self._recent])))
        self._losses, self._masked = [], []

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()

    # --- the algorithm -------------------------------------------------------------------------
    def _end_episode(self, env_index: int, info: Mapping[str, Any]) -> None:
        if self.trainer is not None:
            for decision in self._staged[env_index]:
                self.buffer.add(*decision)
            self._staged[env_index] = []
            self.buffer.end_episode()
            self._losses.append(self.trainer.on_episode_end(self.buffer, self.rng))
        self.episodes += 1
        row = episode_row(info, self.episodes, self.num_timesteps, self.masks_on)
        self.history.append(row)
        self._recent.append(row)
        if self._bar is not None:
            self._bar.update()
            self._bar.set_postfix(
                success=f"{np.mean([e['success'] for e in self._recent]):.2f}", refresh=False
            )
        if (
            not self.masks_on
            and self.predictor is not None
            and self.episodes >= self.settings.mask_after_episodes
        ):
            self.masks_on = True
            self.push_masks()
        if self.checkpoint_dir is not None and self.episodes % self.settings.save_every_episodes == 0:
            self.save(self.checkpoint_dir, with_model=True)

    def push_masks(self) -> None:
        """Give every env worker a GCCP mask with a copy of the current predictor."""
        assert self.predictor is not None
        predictor = copy.deepcopy(self.predictor).cpu().eval()
        self.training_env.env_method("set_mask_fn", self.settings.make_mask(predictor))

    # --- saving and resuming -------------------------------------------------------------------
    def save(self, folder: Path, with_model: bool = False) -> None:
        """Write the callback's state (and, with ``with_model``, the model) into ``folder``."""
        folder.mkdir(parents=True, exist_ok=True)
        if with_model:
            self.model.save(folder / "decider.zip")
        if isinstance(self.predictor, TrajectoryPredictor):
            save_predictor(self.predictor, folder / "predictor.pt")
        if self.trainer is not None:
            self.buffer.save(folder / "buffer.npz")
        state = {
            "episodes": self.episodes,
            "masks_on": self.masks_on,
            "optimizer": self.trainer.optimizer.state_dict() if self.trainer is not None else {},
            "gradient_steps": self.trainer.gradient_steps if self.trainer is not None else 0,
        }
        th.save(state, folder / "gccp_state.pt")
        write_episodes(self.history, folder / "episodes.csv")

    def restore(self, folder: Path) -> None:
        """Read the state written by :meth:`save` (the predictor's weights are loaded by the caller)."""
        state = th.load(folder / "gccp_state.pt", weights_only=True)
        self.episodes = int(state["episodes"])
        self.masks_on = bool(state["masks_on"])
        if self.trainer is not None:
            self.trainer.optimizer.load_state_dict(state["optimizer"])
            self.trainer.gradient_steps = int(state["gradient_steps"])
        self.history = read_episodes(folder / "episodes.csv")
        self._recent.extend(self.history[-100:])


def episode_row(info: Mapping[str, Any], episode: int, timesteps: int, masks_on: bool) -> dict[str, Any]:
    """One row of ``episodes.csv`` from the final ``info`` of an episode."""
    return {
        "episode": episode,
        "timesteps": timesteps,
        "task": info.get("task", ""),
        "success": int(bool(info.get("is_success"))),
        "crashed": int(bool(info.get("crashed"))),
        "offroad": int(bool(info.get("offroad"))),
        "timeout": int(bool(info.get("timeout"))),
        "masks_on": int(masks_on),
    }


def write_episodes(rows: list[dict[str, Any]], path: Path) -> None:
    """One CSV row per training episode."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=EPISODE_FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def read_episodes(path: Path) -> list[dict[str, Any]]:
    """The rows written by :func:`write_episodes` (numbers as ints)."""
    if not path.is_file():
        return []
    with path.open(newline="") as file:
        return [{k: v if k == "task" else int(v) for k, v in row.items()} for row in csv.DictReader(file)]
