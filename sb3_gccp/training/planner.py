"""Training stages. A run folder holds everything a run needs to be inspected, resumed or evaluated.

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

import json
import math
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from sb3_contrib import MaskablePPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback, StopTrainingOnMaxEpisodes
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from gccp_envs.config import IntersectionConfig
from sb3_gccp.hyperparams import (
    HyperparamsError,
    check_keys,
    gradient_steps_per_timestep,
    load_hyperparams,
    resolve_class,
    resolve_policy_kwargs,
    resolve_schedule,
)
from sb3_gccp.imitation import BehaviourCloningCallback, ExpertData, ImitationSettings, imitate
from sb3_gccp.progress import StepBar

PLANNER_ENV_ID = "GCCPPlanner-v0"


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
    runs = [p for p in stage_dir.glob("*") if (p / "config.yml").is_file()]
    return max(runs, key=lambda p: (p / "config.yml").stat().st_mtime, default=None)


def train_planner(request: StageRequest) -> Path:
    """Train the motion-planner with MaskablePPO on ``GCCPPlanner-v0``; return the model path.

    With an ``imitation`` map in the entry, the policy first clones a scripted expert planner, with
    DAgger rounds if asked (:mod:`sb3_gccp.imitation`; ``imitation.json`` records how well, and the
    clone is saved as ``planner_cloned.zip``), and PPO continues from there for ``n_timesteps`` (0:
    cloning only), with cloning steps between its updates if ``imitation.bc_steps`` asks. With
    ``request.resume`` (a run folder), training continues from its last checkpoint with the run's own
    resolved config, up to the same total budget.
    """
    if request.torch_threads is not None:
        th.set_num_threads(request.torch_threads)
    run_dir, settings, seed = open_run(request, PLANNER_ENV_ID, "planner")
    imitation = imitation_settings(settings)
    world, n_timesteps, n_envs = run_budget(settings, (IMITATION_KEY,), allow_zero=imitation is not None)
    if request.resume is None:
        write_run_files(run_dir, settings, request)
    env = make_run_env(PLANNER_ENV_ID, n_envs, seed, world, run_dir)
    checkpoint = latest_checkpoint(run_dir) if request.resume is not None else None
    ppo_settings = {k: v for k, v in settings.items() if k != IMITATION_KEY}
    model = make_model(
        env, run_dir, checkpoint, seed, request.verbose, algorithm_kwargs(ppo_settings, n_timesteps)
    )
    callbacks: list[BaseCallback] = [
        CheckpointCallback(
            max(request.save_freq // n_envs, 1), str(run_dir / "checkpoints"), name_prefix="planner"
        )
    ]
    if imitation is not None:
        data = imitation_data(model, run_dir, world, imitation, seed, checkpoint, request.progress_bar)
        if imitation.bc_steps > 0:
            callbacks.append(BehaviourCloningCallback(data, imitation, seed))
    if request.progress_bar:
        callbacks.append(StepBar(n_timesteps))
    if request.max_episodes is not None:
        # SB3 counts the limit per worker.
        callbacks.append(StopTrainingOnMaxEpisodes(math.ceil(request.max_episodes / n_envs)))
    remaining = n_timesteps - model.num_timesteps
    try:
        if remaining > 0:
            model.learn(
                remaining,
                callback=callbacks,
                reset_num_timesteps=checkpoint is None,
                tb_log_name="planner",
            )
    finally:
        env.close()
    path = run_dir / "planner.zip"
    model.save(path)
    return path


CLONED_PLANNER = "planner_cloned.zip"
"""The planner as cloned, before PPO, in the run folder of a planner stage with ``imitation``."""
IMITATION_DATA = "imitation_data.npz"
"""The cloning's data set in the run folder (the behaviour-cloning term of PPO reads it on resume)."""


def imitation_data(
    model: MaskablePPO,
    run_dir: Path,
    world: IntersectionConfig,
    settings: ImitationSettings,
    seed: int,
    checkpoint: Path | None,
    progress: bool,
) -> ExpertData:
    """A new run clones the expert into ``model`` (writing ``imitation.json``, the cloned planner and,
    if PPO keeps a cloning term, the data set); a resumed one reads the data set back."""
    path = run_dir / IMITATION_DATA
    if checkpoint is not None:
        if settings.bc_steps == 0:
            return ExpertData({}, np.empty(0), np.empty(0), np.empty(0), 0)
        if not path.is_file():
            raise HyperparamsError(f"cannot resume the cloning term: {path} is missing")
        return ExpertData.load(path)
    record, data = imitate(model, world, settings, seed, progress)
    (run_dir / "imitation.json").write_text(json.dumps(record, indent=2) + "\n")
    model.save(run_dir / CLONED_PLANNER)
    if settings.bc_steps > 0:
        data.save(path)
    return data


IMITATION_KEY = "imitation"
"""The planner entry's own key: imitation of a scripted expert planner before PPO."""


def imitation_settings(settings: dict[str, Any]) -> ImitationSettings | None:
    """The planner entry's ``imitation`` map, validated; None without one."""
    if IMITATION_KEY not in settings:
        return None
    try:
        return ImitationSettings.from_dict(settings[IMITATION_KEY])
    except (ValueError, TypeError) as err:
        raise HyperparamsError(str(err)) from err


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
    if not (run_dir / "config.yml").is_file():
        raise HyperparamsError(f"not a run folder (no config.yml): {run_dir}")
    settings = yaml.safe_load((run_dir / "config.yml").read_text())
    return run_dir, settings, int(yaml.safe_load((run_dir / "args.yml").read_text())["seed"])


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
    """The training envs of a run: ``n_envs`` workers (subprocesses when more than one) of ``env_id``
    on ``world``, with Monitor files in ``run_dir/monitor``."""
    return make_vec_env(
        env_id,
        n_envs=n_envs,
        seed=seed,
        env_kwargs={"config": world},
        monitor_dir=str(run_dir / "monitor"),
        vec_env_cls=SubprocVecEnv if n_envs > 1 else DummyVecEnv,
    )


def write_run_files(run_dir: Path, settings: dict[str, Any], request: StageRequest) -> None:
    run_dir.mkdir(parents=True, exist_ok=False)
    (run_dir / "config.yml").write_text(yaml.safe_dump(settings, sort_keys=True))
    args = {
        "config_file": str(request.config_file),
        "seed": request.seed,
        "n_timesteps": request.n_timesteps,
        "log_folder": str(request.log_folder),
        "planner": None if request.planner is None else str(request.planner),
    }
    (run_dir / "args.yml").write_text(yaml.safe_dump(args, sort_keys=True))
    (run_dir / "command.txt").write_text(shlex.join(request.argv) + "\n")
