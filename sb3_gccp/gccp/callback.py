"""The GCCP callback: trains the predictor beside the decision-maker and hands masks to the envs.

Algorithm 1 of the paper, as an SB3 callback on MaskablePPO over ``GCCPDecider-v0``:

- every decision of every training env goes into that env's episode buffer D_e, from the raw features
  the env puts in ``info`` (``decision_obs``, ``subgoal``, ``future``, ``future_mask``), so that a
  ``VecNormalize`` wrapper would not matter;
- at an episode's end D_e moves into the replay buffer D and the predictor takes K_p gradient steps
  on batches of N_b decisions. These wait in a queue, in the order the episodes ended; with the envs
  wrapped in :class:`StepOverlap` one of them runs while the env workers take each step, the rest at
  the rollout's end. The workers see the predictor's weights only when they are pushed, and the queue
  is emptied before that, so a run's results are the same with the wrapper or without;
- from episode N_m on, every env worker masks subgoals with the GCCP module: the callback sends each
  worker a :class:`~sb3_gccp.gccp.mask.GCCPMask` with a copy of the predictor through
  ``VecEnv.env_method("set_mask_fn", ...)`` (``set_attr`` would set the Monitor wrapper), again after
  every rollout so that the workers use the latest weights;
- training stops after N_e episodes.

It logs the predictor loss, ADE/FDE on the latest decisions, the share of masked candidates and the
success and collision rates to TensorBoard, keeps one row per episode for the training curve, and
checkpoints everything needed to resume (model, predictor, optimiser, replay buffer, counters) at the
start of the rollout after every ``save_every_episodes``-th episode: there PPO's last update is done,
so that a resume collects the rollouts an uninterrupted run would.
"""

from __future__ import annotations

import copy
from collections import deque
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn
from torch import nn
from tqdm.auto import tqdm

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import DECIDER_FILE, EPISODES_FILE, PREDICTOR_FILE
from sb3_gccp.gccp.predictor import TrajectoryPredictor, save_predictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer
from sb3_gccp.gccp.settings import LEARNED, GCCPSettings
from sb3_gccp.gccp.training import PredictorTrainer, displacement_errors
from sb3_gccp.progress import new_bar
from sb3_gccp.training.checkpoints import Checkpoint, Writer, save_checkpoint
from sb3_gccp.training.choosing import save_candidate
from sb3_gccp.training.episodes import TrainingClock, episode_row, read_episodes, write_episodes

STATE_FILE = "gccp_state.pt"
"""The callback's counters and the predictor's optimiser, in a checkpoint folder."""
BUFFER_FILE = "buffer.npz"
"""The replay buffer D, in a checkpoint folder."""


class StepOverlap(VecEnvWrapper):
    """Runs some of the learner's waiting work while the env workers step.

    ``step_async`` sends the actions to the workers, then calls ``work`` (the GCCP callback's
    :meth:`GCCPCallback.run_next`: one predictor gradient step), then ``step_wait`` collects the
    workers' results: with a ``SubprocVecEnv`` the predictor's training and the envs' steps share the
    cores instead of taking turns. With a ``DummyVecEnv`` the work simply runs before the step.

    :param venv: the training envs
    :param work: called once per step, between sending the actions and collecting the results
    """

    def __init__(self, venv: VecEnv, work: Callable[[], None]) -> None:
        super().__init__(venv)
        self.work = work

    def step_async(self, actions: np.ndarray) -> None:
        self.venv.step_async(actions)
        self.work()

    def step_wait(self) -> VecEnvStepReturn:
        return self.venv.step_wait()

    def reset(self) -> Any:
        return self.venv.reset()


class GCCPCallback(BaseCallback):
    """Fills the replay buffer, trains the predictor, pushes GCCP masks, stops after N_e episodes.

    :param settings: schedule and predictor training
    :param predictor: the predictor (trained here if learned; ``None`` without GCCP)
    :param buffer: the replay buffer D
    :param seed: seeds the predictor's batch sampling
    :param progress_bar: show a progress bar over episodes
    :param run_dir: the run folder whose ``checkpoints/`` it writes (None: no checkpoints)
    :param world: the world the decider trains in, whose vehicles the masks check (default: ours)
    """

    def __init__(
        self,
        settings: GCCPSettings,
        predictor: nn.Module | None,
        buffer: EpisodeReplayBuffer,
        seed: int = 0,
        progress_bar: bool = False,
        run_dir: Path | None = None,
        world: IntersectionConfig | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.settings = settings
        self.world = world or IntersectionConfig()
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
        self._clock = TrainingClock()
        self.run_dir = run_dir
        self._checkpointed_at = 0
        self._candidate_slot = 0
        self._staged: list[list[tuple[Any, ...]]] = []
        self._waiting: deque[Callable[[], None]] = deque()
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

    def _on_rollout_start(self) -> None:
        every = self.settings.save_every_episodes
        if self.run_dir is not None and self.episodes // every > self._checkpointed_at // every:
            self.checkpoint(self.model)
        slot = self.episodes // self.settings.choose_every_episodes
        if slot > self._candidate_slot:
            self._candidate_slot = slot
            if self.choosing and self.episodes >= self.settings.choose_from_episodes:
                self.save_candidate(self.model)

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
        self.run_waiting()
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
        self.run_waiting()
        if self._bar is not None:
            self._bar.close()

    # --- the algorithm -------------------------------------------------------------------------
    def _end_episode(self, env_index: int, info: Mapping[str, Any]) -> None:
        if self.trainer is not None:
            decisions, self._staged[env_index] = self._staged[env_index], []
            self._waiting.append(partial(self._store_episode, decisions))
            self._waiting.extend([self._predictor_step] * self.trainer.steps_per_episode)
        self.episodes += 1
        row = episode_row(info, self.episodes, self.num_timesteps, self.masks_on, self._clock())
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

    def _store_episode(self, decisions: list[tuple[Any, ...]]) -> None:
        """Move an episode's decisions D_e into the replay buffer D."""
        for decision in decisions:
            self.buffer.add(*decision)
        self.buffer.end_episode()

    def _predictor_step(self) -> None:
        """One of Algorithm 1's K_p predictor steps after an episode."""
        assert self.trainer is not None
        self._losses.append(self.trainer.train_steps(self.buffer, 1, self.rng))

    def run_next(self) -> None:
        """Run the waiting updates up to and with the next predictor step."""
        while self._waiting:
            work = self._waiting.popleft()
            work()
            if work == self._predictor_step:
                return

    def run_waiting(self) -> None:
        """Run every waiting update, in order: the replay buffer and the predictor are then up to date."""
        while self._waiting:
            self.run_next()

    def push_masks(self) -> None:
        """Give every env worker a GCCP mask with a copy of the current predictor."""
        assert self.predictor is not None
        self.run_waiting()
        predictor = copy.deepcopy(self.predictor).cpu().eval()
        self.training_env.env_method("set_mask_fn", self.settings.check.make_mask(predictor, self.world))

    # --- saving and resuming -------------------------------------------------------------------
    def checkpoint(self, model: BaseAlgorithm) -> Checkpoint:
        """Write a checkpoint of ``model`` and of the callback's state into the run folder."""
        assert self.run_dir is not None
        self.run_waiting()
        state = {
            "episodes": self.episodes,
            "masks_on": self.masks_on,
            "optimizer": self.trainer.optimizer.state_dict() if self.trainer is not None else {},
            "gradient_steps": self.trainer.gradient_steps if self.trainer is not None else 0,
            "rng": self.rng.bit_generator.state,
        }
        files: dict[str, Writer] = {DECIDER_FILE: model.save}
        if isinstance(self.predictor, TrajectoryPredictor):
            predictor = self.predictor
            files[PREDICTOR_FILE] = lambda path: save_predictor(predictor, path)
        if self.trainer is not None:
            files[BUFFER_FILE] = self.buffer.save
        files[STATE_FILE] = lambda path: th.save(state, path)
        history = list(self.history)
        files[EPISODES_FILE] = lambda path: write_episodes(history, path)
        self._checkpointed_at = self.episodes
        return save_checkpoint(self.run_dir, "decider", model.num_timesteps, files)

    @property
    def choosing(self) -> bool:
        """Whether the run's model is chosen on validation flows (see ``GCCPSettings.choose_on_flows``)."""
        return self.run_dir is not None and self.settings.choose_on_flows is not None

    def save_candidate(self, model: BaseAlgorithm) -> Path:
        """Write the decider and its predictor as they are now into ``candidates/<episodes>/`` of the run
        folder, for :func:`sb3_gccp.training.choosing.choose_model`."""
        assert self.run_dir is not None
        self.run_waiting()
        return save_candidate(self.run_dir, self.episodes, model, self.predictor)

    def restore(self, checkpoint: Checkpoint) -> None:
        """Read the state written by :meth:`checkpoint` (the model, predictor weights and replay buffer are
        loaded by the caller)."""
        state = th.load(checkpoint.file(STATE_FILE), weights_only=True)
        self.episodes = int(state["episodes"])
        self.masks_on = bool(state["masks_on"])
        if self.trainer is not None:
            self.trainer.optimizer.load_state_dict(state["optimizer"])
            self.trainer.gradient_steps = int(state["gradient_steps"])
        self.rng.bit_generator.state = state["rng"]
        self.history = read_episodes(checkpoint.file(EPISODES_FILE))
        self._clock = TrainingClock(self.history)
        self._recent.extend(self.history[-100:])
        self._checkpointed_at = self.episodes
        self._candidate_slot = self.episodes // self.settings.choose_every_episodes
