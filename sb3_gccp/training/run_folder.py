"""Run folders of the training stages: where a run's files go, and what a stage needs to start one.

Run folder layout (rl-zoo's, plus our checkpoints)::

    <log_folder>/<stage>/<env_id>_<seed>_<time>/
        config.yml      resolved hyperparameters and world config
        args.yml        the command's arguments
        command.txt     the command line
        monitor/        one Monitor CSV per env worker
        tb/             TensorBoard logs
        checkpoints/    <stage>_<steps>_steps.zip every ``save_freq`` steps
        <stage>.zip     the trained model
"""

from __future__ import annotations

import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from sb3_contrib import MaskablePPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import ARGS_FILE, COMMAND_FILE, CONFIG_FILE
from sb3_gccp.hyperparams import (
    HyperparamsError,
    check_keys,
    gradient_steps_per_timestep,
    load_hyperparams,
    resolve_class,
    resolve_policy_kwargs,
    resolve_schedule,
)


@dataclass
class StageRequest:
    """What the user asked of a training stage."""

    config_file: Path
    seed: int = 0
    n_timesteps: int | None = None
    log_folder: Path = Path("runs")
    resume: Path | None = None
    progress_bar: bool = True
    verbose: int = 0
    save_freq: int = 10_000
    """Environment steps between checkpoints (over all workers)."""
    torch_threads: int | None = None
    """Torch threads of the learner process (the env workers use no torch); ``None`` keeps torch's."""
    planner: Path | None = None
    """The frozen motion-planner ``.zip`` (decider stage)."""
    max_episodes: int | None = None
    """Stop the planner stage after this many episodes over all workers (N_g); None: ``n_timesteps``."""
    run_dir: Path | None = None
    """The folder of a new run; None: a new ``<log_folder>/<stage>/<env_id>_<seed>_<time>``."""
    argv: list[str] = field(default_factory=lambda: list(sys.argv))


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint with the most steps in a run folder, if any."""
    checkpoints = list((run_dir / "checkpoints").glob("*_steps.zip"))
    return max(checkpoints, key=lambda p: int(p.stem.split("_")[-2]), default=None)


def latest_run(stage_dir: Path) -> Path | None:
    """The most recently started run folder of a stage, if any."""
    runs = [p for p in stage_dir.glob("*") if (p / CONFIG_FILE).is_file()]
    return max(runs, key=lambda p: (p / CONFIG_FILE).stat().st_mtime, default=None)


def open_run(request: StageRequest, env_id: str, stage: str) -> tuple[Path, dict[str, Any], int]:
    """The run folder, settings and seed of a stage: a new run from the zoo file's ``env_id`` entry, or
    with ``request.resume`` the run's own resolved config and seed. Nothing is written yet."""
    if request.resume is None:
        settings = load_hyperparams(request.config_file, env_id)
        if request.n_timesteps is not None:
            settings["n_timesteps"] = request.n_timesteps
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run_dir = request.run_dir or request.log_folder / stage / f"{env_id}_{request.seed}_{stamp}"
        return run_dir, settings, request.seed
    run_dir = request.resume
    if not (run_dir / CONFIG_FILE).is_file():
        raise HyperparamsError(f"not a run folder (no config.yml): {run_dir}")
    settings = yaml.safe_load((run_dir / CONFIG_FILE).read_text())
    return run_dir, settings, int(yaml.safe_load((run_dir / ARGS_FILE).read_text())["seed"])


def run_budget(
    settings: dict[str, Any], own_keys: tuple[str, ...] = (), allow_zero: bool = False
) -> tuple[IntersectionConfig, int, int]:
    """Check the settings' keys (besides ``own_keys``) against MaskablePPO; the world config,
    ``n_timesteps`` (0 allowed with ``allow_zero``) and ``n_envs``."""
    check_keys({k: v for k, v in settings.items() if k not in own_keys}, MaskablePPO)
    world = IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    n_timesteps = int(settings.get("n_timesteps", 100_000))
    n_envs = int(settings.get("n_envs", 1))
    if n_timesteps < (0 if allow_zero else 1) or n_envs < 1:
        what = "non-negative" if allow_zero else "positive"
        raise HyperparamsError(f"n_timesteps must be {what} and n_envs positive")
    return world, n_timesteps, n_envs


def make_model(
    env: VecEnv, run_dir: Path, checkpoint: Path | None, seed: int, verbose: int, kwargs: dict[str, Any]
) -> MaskablePPO:
    """MaskablePPO logging to ``run_dir/tb``: loaded from ``checkpoint`` if given, else built from
    ``kwargs``."""
    if checkpoint is not None:
        return MaskablePPO.load(checkpoint, env=env, tensorboard_log=str(run_dir / "tb"))
    return MaskablePPO(env=env, tensorboard_log=str(run_dir / "tb"), seed=seed, verbose=verbose, **kwargs)


def algorithm_kwargs(
    settings: dict[str, Any],
    n_timesteps: int,
    default_policy: str = "MotionPlannerPolicy",
    algorithm: type[BaseAlgorithm] = MaskablePPO,
) -> dict[str, Any]:
    """Constructor arguments of ``algorithm`` from resolved settings: step schedules placed on its
    gradient steps for a run of ``n_timesteps``, the policy and the classes in ``policy_kwargs`` imported."""
    kwargs = {k: v for k, v in settings.items() if k not in ("n_timesteps", "n_envs", "env_kwargs", "policy")}
    per_timestep = gradient_steps_per_timestep(algorithm, settings)
    for key in ("learning_rate", "clip_range"):
        if key in kwargs:
            kwargs[key] = resolve_schedule(kwargs[key], key, per_timestep, n_timesteps)
    if kwargs.get("policy_kwargs"):
        kwargs["policy_kwargs"] = resolve_policy_kwargs(kwargs["policy_kwargs"])
    kwargs["policy"] = resolve_class(str(settings.get("policy", default_policy)), algorithm.policy_aliases)
    return kwargs


def make_run_env(env_id: str, n_envs: int, seed: int, world: IntersectionConfig, run_dir: Path) -> VecEnv:
    """The training envs of a run: ``n_envs`` copies of ``env_id`` on ``world``, stepped in the learner's
    process, with Monitor files in ``run_dir/monitor``.

    Not in subprocesses: a step with its action mask takes about 2 ms, and subprocesses would add two
    pipe round trips to each (``step``, then ``action_masks()``); on a shared 2-core machine the planner
    stage trained 1.1-1.6 times as fast without them (docs/experiments/2026-11-26-planner-stage-speed.md).
    """
    return make_vec_env(
        env_id,
        n_envs=n_envs,
        seed=seed,
        env_kwargs={"config": world},
        monitor_dir=str(run_dir / "monitor"),
        vec_env_cls=DummyVecEnv,
    )


def write_run_files(run_dir: Path, settings: dict[str, Any], request: StageRequest) -> None:
    """Make a new run folder with the resolved settings, the arguments and the command line."""
    run_dir.mkdir(parents=True, exist_ok=False)
    (run_dir / CONFIG_FILE).write_text(yaml.safe_dump(settings, sort_keys=True))
    args = {
        "config_file": str(request.config_file),
        "seed": request.seed,
        "n_timesteps": request.n_timesteps,
        "log_folder": str(request.log_folder),
        "planner": None if request.planner is None else str(request.planner),
    }
    (run_dir / ARGS_FILE).write_text(yaml.safe_dump(args, sort_keys=True))
    (run_dir / COMMAND_FILE).write_text(shlex.join(request.argv) + "\n")
