"""The paper's baselines (IV-A-1): DQN, PPO and SAC-Discrete on the flat env ``GCCPFlat-v0``.

Each runs for an episode budget (the paper compares the methods at the same number of episodes) with
the motion-planner's networks, named in its zoo file (``zoo_configs/dqn.yml``, ``ppo.yml``,
``sac_discrete.yml``, entry ``GCCPFlat-v0``). Run folder::

    config.yml      the resolved zoo entry
    baseline.yml    the algorithm's name and the model file (``sb3_gccp evaluate --model RUN`` reads it)
    model.zip       the trained model (``<Algorithm>.load``)
    episodes.csv    one row per training episode, as the decider's (task, success, crash, wall clock)
    monitor/, tb/   Monitor CSVs and TensorBoard logs
    checkpoints/    every ``save_every_episodes``: model.zip, replay_buffer.pkl (off-policy
                    algorithms), episodes.csv; ``train_baseline(..., resume=True)`` continues from them

With ``action_masks: true`` in the entry (the shipped files' setting; sb3_gccp's own key) a baseline
gets the motion-planner's road-keeping mask (the flat env's ``action_masks()``) in training and in
evaluation: PPO is MaskablePPO, DQN is :class:`~sb3_gccp.maskable_dqn.MaskableDQN` (masked greedy,
masked exploration) and SAC-Discrete takes a masked softmax; the last two read the mask from the
observation (:mod:`sb3_gccp.action_masks`). ``action_masks: false`` (or no key, as in run folders
from before the key) is the paper's unmasked baseline. Either way a baseline is evaluated with its
policy's ``predict(obs, deterministic=True)``, the policy rebuilt without unpickling
(:mod:`sb3_gccp.safe_loading`).
"""

from __future__ import annotations

import math
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from tqdm.auto import tqdm

from gccp_envs.config import DT, IntersectionConfig
from sb3_gccp.action_masks import ActionMaskObservation
from sb3_gccp.constants import BASELINE_FILE, CONFIG_FILE, EPISODES_FILE, FLAT_ENV_ID, MODEL_FILE
from sb3_gccp.evaluation import Policy
from sb3_gccp.hyperparams import check_keys, load_hyperparams, read_yaml_mapping, resolve_class
from sb3_gccp.progress import new_bar
from sb3_gccp.safe_loading import PolicyKind, file_in_folder, load_policy
from sb3_gccp.training.episodes import TrainingClock, episode_row, read_episodes, write_episodes
from sb3_gccp.training.run_folder import algorithm_kwargs, make_run_env

BASELINES = {
    "dqn": "stable_baselines3.DQN",
    "ppo": "stable_baselines3.PPO",
    "sac_discrete": "sb3_gccp.sac_discrete.SACDiscrete",
}
"""Baseline name (and zoo file ``<name>.yml``) -> its algorithm class, imported when first used."""
MASKED_BASELINES = {
    "dqn": "sb3_gccp.maskable_dqn.MaskableDQN",
    "ppo": "sb3_contrib.MaskablePPO",
    "sac_discrete": "sb3_gccp.sac_discrete.SACDiscrete",
}
"""The same with action masks (``action_masks: true``)."""
MASKS_KEY = "action_masks"
"""sb3_gccp's own key of a baseline's zoo entry: train and evaluate with the flat env's action masks."""
MASKS_IN_OBSERVATION = ("dqn", "sac_discrete")
"""Masked baselines that read the mask from the observation (the others ask the env)."""
REPLAY_BUFFER_FILE = "replay_buffer.pkl"
"""An off-policy baseline's replay buffer, in its checkpoint folder."""


def baseline_algorithm(name: str, masked: bool = False) -> type[BaseAlgorithm]:
    """The algorithm class of a baseline, with action masks or without.

    :raises ValueError: an unknown name
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}: expected one of {', '.join(BASELINES)}")
    return resolve_class((MASKED_BASELINES if masked else BASELINES)[name])


def uses_masks(settings: dict[str, Any]) -> bool:
    """Whether a baseline entry (or a run's config.yml) trains with action masks.

    :raises ValueError: a value that is not true or false
    """
    masked = settings.get(MASKS_KEY, False)
    if not isinstance(masked, bool):
        raise ValueError(f"{MASKS_KEY} must be true or false, got {masked!r}")
    return masked


def flat_env(name: str, masked: bool, **kwargs: Any) -> gym.Env:
    """``GCCPFlat-v0`` as a baseline sees it: with the action mask in its observation when the masked
    baseline reads it from there."""
    env = gym.make(FLAT_ENV_ID, **kwargs)
    return ActionMaskObservation(env) if masked and name in MASKS_IN_OBSERVATION else env


def max_episode_steps(world: IntersectionConfig) -> int:
    """The longest episode in env steps (the ``duration`` limit)."""
    return math.ceil(world.duration / DT - 1e-9)


class EpisodeRecorder(BaseCallback):
    """One row per finished training episode (the decider's ``episodes.csv`` layout), a progress bar,
    a checkpoint at the end of the rollout in which every ``save_every``-th episode ended, and the end
    of training at the episode budget.

    :param budget: the episode budget over all workers
    :param description: the progress bar's label
    :param progress_bar: show the bar
    :param checkpoint_dir: where checkpoints go (None: no checkpoints)
    :param save_every: episodes between checkpoints
    :param history: the rows of a resumed run
    """

    def __init__(
        self,
        budget: int,
        description: str = "",
        progress_bar: bool = False,
        checkpoint_dir: Path | None = None,
        save_every: int = 250,
        history: list[dict[str, Any]] | None = None,
    ) -> None:
        super().__init__()
        self.budget = budget
        self.description = description
        self.progress_bar = progress_bar
        self.checkpoint_dir = checkpoint_dir
        self.save_every = save_every
        self.history: list[dict[str, Any]] = list(history or [])
        self._clock = TrainingClock(self.history)
        self._bar: tqdm | None = None
        self._checkpoint_due = False

    def _on_training_start(self) -> None:
        self._bar = new_bar(
            total=self.budget,
            initial=len(self.history),
            desc=self.description,
            unit="ep",
            enabled=self.progress_bar,
        )

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
            if done and len(self.history) < self.budget:
                row = episode_row(info, len(self.history) + 1, self.num_timesteps, False, self._clock())
                self.history.append(row)
                if self._bar is not None:
                    self._bar.update()
                self._checkpoint_due |= len(self.history) % self.save_every == 0
        return len(self.history) < self.budget

    def _on_rollout_end(self) -> None:
        # Here every transition collected so far is in the replay buffer (in _on_step the last one
        # is not yet); an on-policy rollout is simply collected again after a resume.
        if self._checkpoint_due and self.checkpoint_dir is not None:
            self.save_checkpoint(self.checkpoint_dir)
        self._checkpoint_due = False

    def save_checkpoint(self, folder: Path) -> None:
        """The model, its replay buffer (off-policy) and the episode rows, each written then renamed."""
        folder.mkdir(parents=True, exist_ok=True)
        self.model.save(folder / "model.tmp.zip")
        if isinstance(self.model, OffPolicyAlgorithm):
            self.model.save_replay_buffer(folder / "replay_buffer.tmp.pkl")
            (folder / "replay_buffer.tmp.pkl").replace(folder / REPLAY_BUFFER_FILE)
        write_episodes(self.history, folder / "episodes.tmp.csv")
        (folder / "model.tmp.zip").replace(folder / MODEL_FILE)
        (folder / "episodes.tmp.csv").replace(folder / EPISODES_FILE)  # last: marks the set complete

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()


def train_baseline(
    name: str,
    config_file: Path,
    run_dir: Path,
    seed: int,
    episodes: int,
    progress_bar: bool = False,
    description: str = "",
    resume: bool = False,
    save_every_episodes: int = 250,
    callback: BaseCallback | None = None,
) -> Path:
    """Train a baseline on ``GCCPFlat-v0`` for ``episodes`` episodes over all workers; return the model.

    :param name: ``dqn``, ``ppo`` or ``sac_discrete``
    :param config_file: a zoo file with a ``GCCPFlat-v0`` entry
    :param run_dir: the run folder (created; must not exist unless resuming)
    :param seed: seed of the algorithm and of the env workers
    :param episodes: the episode budget; ``n_timesteps`` of the entry only caps the run
    :param progress_bar: count episodes on a progress bar labelled ``description``
    :param resume: continue ``run_dir`` from its last checkpoint (model, replay buffer, episode rows,
        step count and schedules; the env workers start over from ``seed``)
    :param save_every_episodes: episodes between checkpoints
    :param callback: an extra SB3 callback beside the episode recorder (``sb3_gccp tune``'s pruning)
    """
    settings = load_hyperparams(config_file, FLAT_ENV_ID)
    masked = uses_masks(settings)
    algorithm = baseline_algorithm(name, masked)
    own = {k: v for k, v in settings.items() if k != MASKS_KEY}
    check_keys(own, algorithm)
    world = IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    n_timesteps, n_envs = int(settings.get("n_timesteps", 1)), int(settings.get("n_envs", 1))
    kwargs = algorithm_kwargs(own, n_timesteps, "MultiInputPolicy", algorithm)
    checkpoints = run_dir / "checkpoints"
    if resume and not has_checkpoint(run_dir):
        raise ValueError(f"no checkpoint to resume in {run_dir}")
    if not resume:
        run_dir.mkdir(parents=True, exist_ok=False)
        (run_dir / CONFIG_FILE).write_text(yaml.safe_dump(settings, sort_keys=True))
    env = make_run_env(partial(flat_env, name, masked), n_envs, seed, {"config": world}, run_dir)
    history = read_episodes(checkpoints / EPISODES_FILE) if resume else []
    recorder = EpisodeRecorder(episodes, description, progress_bar, checkpoints, save_every_episodes, history)
    try:
        if resume:
            model = algorithm.load(checkpoints / MODEL_FILE, env=env, device="cpu")
            if isinstance(model, OffPolicyAlgorithm):
                model.load_replay_buffer(checkpoints / REPLAY_BUFFER_FILE)
        else:
            model = algorithm(env=env, seed=seed, tensorboard_log=str(run_dir / "tb"), **kwargs)
        if len(history) < episodes:
            model.learn(
                n_timesteps - model.num_timesteps,
                callback=recorder if callback is None else [recorder, callback],
                tb_log_name=name,
                reset_num_timesteps=not resume,
            )
    finally:
        env.close()
    model.save(run_dir / MODEL_FILE)
    write_baseline_spec(run_dir, name, masked)
    write_episodes(recorder.history, run_dir / EPISODES_FILE)
    return run_dir / MODEL_FILE


def has_checkpoint(run_dir: Path) -> bool:
    """Whether a baseline run folder holds a complete checkpoint to resume from."""
    return (run_dir / "checkpoints" / EPISODES_FILE).is_file()


def write_baseline_spec(run_dir: Path, name: str, masked: bool) -> None:
    """Name the algorithm, its action masks and the model of a baseline run folder in its
    ``baseline.yml``."""
    (run_dir / BASELINE_FILE).write_text(baseline_spec(name, masked))


def baseline_spec(name: str, masked: bool) -> str:
    """The text of a ``baseline.yml``: the algorithm, its action masks and the model file."""
    return yaml.safe_dump({"algorithm": name, MASKS_KEY: masked, "model": MODEL_FILE}, sort_keys=False)


def read_baseline_spec(run_dir: Path) -> tuple[str, bool, Path]:
    """The algorithm's name, whether it uses action masks (no key: it does not) and the model file
    named by a run folder's ``baseline.yml``, all checked.

    :raises ValueError: with a one-line reason when something is missing
    """
    spec = read_yaml_mapping(run_dir / BASELINE_FILE, "baseline file")
    name = str(spec.get("algorithm"))
    masked = uses_masks(spec)
    model = file_in_folder(run_dir, str(spec.get("model", MODEL_FILE)), f"{run_dir / BASELINE_FILE}: model")
    baseline_algorithm(name)
    if not model.is_file():
        raise ValueError(f"{run_dir / BASELINE_FILE} names a missing file: {model}")
    if not (run_dir / CONFIG_FILE).is_file():
        raise ValueError(f"no config.yml in {run_dir}")
    return name, masked, model


def load_baseline(
    run_dir: Path, overrides: dict[str, Any] | None = None, trusted: bool = False
) -> tuple[gym.Env, Policy, str]:
    """A baseline run folder (``baseline.yml``, ``config.yml``, the model) ready to evaluate.

    :param overrides: world config keys replacing the run's
    :param trusted: load the model through its algorithm's ``load`` (which runs code pickled in it)
    :return: ``GCCPFlat-v0`` on the run's world config, the evaluation policy and the algorithm's name
    :raises ValueError: with a one-line reason when something is missing, cannot be read or does not fit
    """
    name, masked, model = read_baseline_spec(run_dir)
    settings = read_yaml_mapping(run_dir / CONFIG_FILE, "run config")
    world = IntersectionConfig.from_dict({**(settings.get("env_kwargs") or {}), **(overrides or {})})
    env = flat_env(name, masked, config=world)
    return env, baseline_policy(name, model, env, trusted, masked), name


def baseline_policy(
    name: str, path: Path, env: gym.Env, trusted: bool = False, masked: bool = False
) -> Policy:
    """A trained baseline as an evaluation policy for ``env`` (its spaces checked): deterministic, with
    the action masks when it was trained with them (MaskablePPO is handed them; the others read them
    from the observation)."""
    kind = PolicyKind(f"{name} baseline", baseline_algorithm(name, masked))
    policy = load_policy(path, kind, env.observation_space, env.action_space, trusted)
    hand_masks = masked and name not in MASKS_IN_OBSERVATION

    def act(obs: dict[str, np.ndarray], action_mask: np.ndarray) -> int:
        if hand_masks:
            action, _ = policy.predict(obs, deterministic=True, action_masks=action_mask)  # type: ignore[call-arg]
        else:
            action, _ = policy.predict(obs, deterministic=True)
        return int(action)

    return act
