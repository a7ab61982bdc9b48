"""The paper's baselines (IV-A-1): DQN, PPO and SAC-Discrete on the flat env ``GCCPFlat-v0``.

Each runs for an episode budget (the paper compares the methods at the same number of episodes) with
the motion-planner's networks, named in its zoo file (``zoo_configs/dqn.yml``, ``ppo.yml``,
``sac_discrete.yml``, entry ``GCCPFlat-v0``). Run folder::

    config.yml      the resolved zoo entry
    baseline.yml    the algorithm's name and the model file (``sb3_gccp evaluate --model RUN`` reads it)
    model.zip       the trained model (``<Algorithm>.load``)
    episodes.csv    one row per training episode, in the layout of the decider's (task, success, crash)
    monitor/, tb/   Monitor CSVs and TensorBoard logs

The baselines have no action masks: they are evaluated with ``model.predict(obs, deterministic=True)``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnMaxEpisodes
from tqdm.auto import tqdm

from gccp_envs.config import DT, IntersectionConfig
from sb3_gccp.callbacks import episode_row, write_episodes
from sb3_gccp.evaluation import Policy
from sb3_gccp.hyperparams import check_keys, load_hyperparams, read_yaml_mapping, resolve_class
from sb3_gccp.progress import new_bar
from sb3_gccp.stages import algorithm_kwargs, make_run_env

FLAT_ENV_ID = "GCCPFlat-v0"
BASELINES = {
    "dqn": "stable_baselines3.DQN",
    "ppo": "stable_baselines3.PPO",
    "sac_discrete": "sb3_gccp.sac_discrete.SACDiscrete",
}
"""Baseline name (and zoo file ``<name>.yml``) -> its algorithm class, imported when first used."""
MODEL_FILE = "model.zip"
BASELINE_FILE = "baseline.yml"


def baseline_algorithm(name: str) -> type[BaseAlgorithm]:
    """The algorithm class of a baseline.

    :raises ValueError: an unknown name
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}: expected one of {', '.join(BASELINES)}")
    return resolve_class(BASELINES[name])


def max_episode_steps(world: IntersectionConfig) -> int:
    """The longest episode in env steps (the ``duration`` limit)."""
    return math.ceil(world.duration / DT - 1e-9)


class EpisodeRecorder(BaseCallback):
    """One row per finished training episode (the decider's ``episodes.csv`` layout) and a progress bar.

    :param budget: the episode budget (the progress bar's total)
    :param description: the progress bar's label
    :param progress_bar: show the bar
    """

    def __init__(self, budget: int, description: str = "", progress_bar: bool = False) -> None:
        super().__init__()
        self.budget = budget
        self.description = description
        self.progress_bar = progress_bar
        self.history: list[dict[str, Any]] = []
        self._bar: tqdm | None = None

    def _on_training_start(self) -> None:
        self._bar = new_bar(total=self.budget, desc=self.description, unit="ep", enabled=self.progress_bar)

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
            if done:
                self.history.append(episode_row(info, len(self.history) + 1, self.num_timesteps, False))
                if self._bar is not None:
                    self._bar.update()
        return True

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
) -> Path:
    """Train a baseline on ``GCCPFlat-v0`` for ``episodes`` episodes over all workers; return the model.

    :param name: ``dqn``, ``ppo`` or ``sac_discrete``
    :param config_file: a zoo file with a ``GCCPFlat-v0`` entry
    :param run_dir: the run folder (created; must not exist)
    :param seed: seed of the algorithm and of the env workers
    :param episodes: the episode budget; ``n_timesteps`` of the entry only caps the run
    :param progress_bar: count episodes on a progress bar labelled ``description``
    """
    algorithm = baseline_algorithm(name)
    settings = load_hyperparams(config_file, FLAT_ENV_ID)
    check_keys(settings, algorithm)
    world = IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    n_timesteps, n_envs = int(settings.get("n_timesteps", 1)), int(settings.get("n_envs", 1))
    kwargs = algorithm_kwargs(settings, n_timesteps, "MultiInputPolicy", algorithm)
    run_dir.mkdir(parents=True, exist_ok=False)
    (run_dir / "config.yml").write_text(yaml.safe_dump(settings, sort_keys=True))
    env = make_run_env(FLAT_ENV_ID, n_envs, seed, world, run_dir)
    recorder = EpisodeRecorder(episodes, description, progress_bar)
    try:
        model = algorithm(env=env, seed=seed, tensorboard_log=str(run_dir / "tb"), **kwargs)
        # SB3 counts the limit per worker.
        stop = StopTrainingOnMaxEpisodes(math.ceil(episodes / n_envs))
        model.learn(n_timesteps, callback=[recorder, stop], tb_log_name=name)
    finally:
        env.close()
    model.save(run_dir / MODEL_FILE)
    write_baseline_spec(run_dir, name)
    write_episodes(recorder.history, run_dir / "episodes.csv")
    return run_dir / MODEL_FILE


def write_baseline_spec(run_dir: Path, name: str) -> None:
    """Name the algorithm and the model of a baseline run folder in its ``baseline.yml``."""
    (run_dir / BASELINE_FILE).write_text(yaml.safe_dump({"algorithm": name, "model": MODEL_FILE}))


def load_baseline(run_dir: Path, overrides: dict[str, Any] | None = None) -> tuple[gym.Env, Policy, str]:
    """A baseline run folder (``baseline.yml``, ``config.yml``, the model) ready to evaluate.

    :param overrides: world config keys replacing the run's

    :return: ``GCCPFlat-v0`` on the run's world config, the evaluation policy and the algorithm's name
    :raises ValueError: with a one-line reason when something is missing
    """
    spec = read_yaml_mapping(run_dir / BASELINE_FILE, "baseline file")
    name, model = str(spec.get("algorithm")), run_dir / str(spec.get("model", MODEL_FILE))
    baseline_algorithm(name)
    if not model.is_file():
        raise ValueError(f"{run_dir / BASELINE_FILE} names a missing file: {model}")
    settings = read_yaml_mapping(run_dir / "config.yml", "run config")
    world = IntersectionConfig.from_dict({**(settings.get("env_kwargs") or {}), **(overrides or {})})
    return gym.make(FLAT_ENV_ID, config=world), baseline_policy(name, model), name


def baseline_policy(name: str, path: Path) -> Policy:
    """A trained baseline as an evaluation policy: deterministic, action masks ignored (it has none)."""
    model = baseline_algorithm(name).load(path, device="cpu")

    def act(obs: dict[str, np.ndarray], action_mask: np.ndarray) -> int:
        action, _ = model.predict(obs, deterministic=True)
        return int(action)

    return act
