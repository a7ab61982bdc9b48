"""Run folders of the training stages: where a run's files go, and what a stage needs to start one.

Run folder layout (rl-zoo's, plus our checkpoints)::

    <log_folder>/<stage>/<env_id>_<seed>_<time>/
        config.yml      resolved hyperparameters and world config
        args.yml        the command's arguments and the run's options (:class:`RunOptions`)
        command.txt     the command line, and that of every resume after it
        monitor/        one Monitor CSV per env worker
        tb/             TensorBoard logs
        checkpoints/    the two newest checkpoints (:mod:`sb3_gccp.training.checkpoints`)
        <stage>.zip     the trained model

A resume continues from the newest complete checkpoint: the Monitor files are cut back to it and
appended to, the env workers and torch are seeded with the run's seed plus the checkpoint's step count
(the run's first episodes are not played again), and the options of ``args.yml`` hold unless given
again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shlex
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml
from sb3_contrib import MaskablePPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from gccp_envs.config import IntersectionConfig, require_int
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
from sb3_gccp.training.checkpoints import (
    MONITOR_DIR,
    Checkpoint,
    Writer,
    find_checkpoint,
    monitor_start_times,
    resume_message,
    rewind_run,
    write_atomically,
)


@dataclass(frozen=True)
class RunOptions:
    """How a run trains, as opposed to what it learns: kept in ``args.yml`` and reused on resume."""

    save_freq: int = 10_000
    """Planner stage: environment steps (over all workers) between checkpoints, each taken after the
    next PPO update (the decider stage checkpoints every ``gccp.save_every_episodes`` episodes)."""
    verbose: int = 0
    """SB3's verbosity: 0 quiet, 1 training statistics, 2 debug."""
    torch_threads: int = 1
    """Torch threads of the learner process (1: the networks are small and the env workers need the
    other cores)."""
    progress_bar: bool = True
    """A progress bar (a plain line a minute when stderr is a file)."""

    def __post_init__(self) -> None:
        require_int("--save-freq", self.save_freq)
        require_int("-v/--verbose", self.verbose, minimum=0)
        require_int("--torch-threads", self.torch_threads)
        if not isinstance(self.progress_bar, bool):
            raise ValueError(f"progress_bar must be true or false, got {self.progress_bar!r}")

    @classmethod
    def resolve(cls, given: Mapping[str, Any], recorded: Mapping[str, Any] | None = None) -> RunOptions:
        """The options ``given`` (None: not given), else the ``recorded`` ones of a resumed run, else the
        defaults.

        :raises ValueError: one line naming an option out of range
        """
        names = [f.name for f in dataclasses.fields(cls)]
        values = {k: v for k, v in (recorded or {}).items() if k in names}
        values.update({k: v for k, v in given.items() if v is not None})
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """The options as plain data for ``args.yml``."""
        return dataclasses.asdict(self)


@dataclass
class StageRequest:
    """What the user asked of a training stage.

    The run options (``progress_bar``, ``verbose``, ``save_freq``, ``torch_threads``) are None when not
    given: a resumed run keeps its own, a new run takes :class:`RunOptions`' defaults.
    """

    config_file: Path
    seed: int = 0
    n_timesteps: int | None = None
    log_folder: Path = Path("runs")
    resume: Path | None = None
    progress_bar: bool | None = None
    verbose: int | None = None
    save_freq: int | None = None
    """Environment steps between checkpoints (over all workers, planner stage)."""
    torch_threads: int | None = None
    """Torch threads of the learner process (the env workers use one each)."""
    planner: Path | None = None
    """The frozen motion-planner ``.zip`` (decider stage)."""
    max_episodes: int | None = None
    """Stop the planner stage after this many episodes over all workers (N_g); None: ``n_timesteps``."""
    run_dir: Path | None = None
    """The folder of a new run; None: a new ``<log_folder>/<stage>/<env_id>_<seed>_<time>``."""
    world: dict[str, Any] = field(default_factory=dict)
    """World config keys replacing those of the entry's ``env_kwargs`` (``--set``; a new run only)."""
    gccp: dict[str, Any] = field(default_factory=dict)
    """Keys replacing those of the decider entry's ``gccp`` map (``--gccp``; a new decider run only)."""
    argv: list[str] = field(default_factory=lambda: list(sys.argv))

    def given_options(self) -> dict[str, Any]:
        """The run options of the request, None where not given."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(RunOptions)}


@dataclass(frozen=True)
class Run:
    """A stage's run: its folder, resolved settings, seed and options, and whether it is resumed."""

    dir: Path
    settings: dict[str, Any]
    seed: int
    options: RunOptions
    resumed: bool


def latest_run(stage_dir: Path) -> Path | None:
    """The most recently started run folder of a stage, if any."""
    runs = [p for p in stage_dir.glob("*") if (p / CONFIG_FILE).is_file()]
    return max(runs, key=lambda p: (p / CONFIG_FILE).stat().st_mtime, default=None)


def requested_settings(request: StageRequest, env_id: str) -> dict[str, Any]:
    """The zoo file's ``env_id`` entry with what the request replaces: world keys (``--set``), ``gccp``
    keys (``--gccp``) and ``n_timesteps``.

    :raises HyperparamsError: the file or the entry cannot be read
    """
    settings = load_hyperparams(request.config_file, env_id)
    if request.world:
        settings["env_kwargs"] = {**(settings.get("env_kwargs") or {}), **request.world}
    if request.gccp:
        settings["gccp"] = {**(settings.get("gccp") or {}), **request.gccp}
    if request.n_timesteps is not None:
        settings["n_timesteps"] = request.n_timesteps
    return settings


def open_run(request: StageRequest, env_id: str, stage: str) -> Run:
    """The run of a stage: a new one from the zoo file's ``env_id`` entry, or with ``request.resume``
    the run's own resolved config, seed and options (those given again replace them). Nothing is
    written yet.

    :raises HyperparamsError: not a run folder
    :raises ValueError: one line naming an option out of range
    """
    if request.resume is None:
        options = RunOptions.resolve(request.given_options())
        settings = requested_settings(request, env_id)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run_dir = request.run_dir or request.log_folder / stage / f"{env_id}_{request.seed}_{stamp}"
        return Run(run_dir, settings, request.seed, options, resumed=False)
    run_dir = request.resume
    if not (run_dir / CONFIG_FILE).is_file():
        raise HyperparamsError(f"not a run folder (no config.yml): {run_dir}")
    settings = yaml.safe_load((run_dir / CONFIG_FILE).read_text())
    args = yaml.safe_load((run_dir / ARGS_FILE).read_text())
    options = RunOptions.resolve(request.given_options(), args)
    return Run(run_dir, settings, int(args["seed"]), options, resumed=True)


def resume_checkpoint(run: Run) -> Checkpoint | None:
    """The checkpoint a resumed run continues from (None for a new run, or when none is complete),
    announced in one line. Nothing is written yet."""
    if not run.resumed:
        return None
    checkpoint, damaged = find_checkpoint(run.dir)
    print(resume_message(run.dir, checkpoint, damaged), flush=True)
    return checkpoint


def run_budget(
    settings: dict[str, Any], own_keys: tuple[str, ...] = (), allow_zero: bool = False
) -> tuple[IntersectionConfig, int, int]:
    """Check the settings' keys (besides ``own_keys``) and batch arithmetic against MaskablePPO; the world
    config, ``n_timesteps`` (0 allowed with ``allow_zero``) and ``n_envs``."""
    check_keys({k: v for k, v in settings.items() if k not in own_keys}, MaskablePPO)
    gradient_steps_per_timestep(MaskablePPO, settings)
    world = IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    n_timesteps = int(settings.get("n_timesteps", 100_000))
    n_envs = int(settings.get("n_envs", 1))
    if n_timesteps < (0 if allow_zero else 1) or n_envs < 1:
        what = "non-negative" if allow_zero else "positive"
        raise HyperparamsError(f"n_timesteps must be {what} and n_envs positive")
    return world, n_timesteps, n_envs


def new_model(env: VecEnv, run: Run, kwargs: dict[str, Any]) -> MaskablePPO:
    """MaskablePPO built from ``kwargs``, seeded with the run's seed, logging to ``tb/``."""
    return MaskablePPO(
        env=env, tensorboard_log=str(run.dir / "tb"), seed=run.seed, verbose=run.options.verbose, **kwargs
    )


def load_model(path: Path, run: Run) -> MaskablePPO:
    """MaskablePPO from a checkpoint's ``.zip``, with the run's verbosity, logging to ``tb/``; it gets its
    envs from :func:`continue_model`."""
    return MaskablePPO.load(path, tensorboard_log=str(run.dir / "tb"), verbose=run.options.verbose)


def continue_model(model: MaskablePPO, env: VecEnv, run: Run) -> None:
    """Give a model loaded from a checkpoint the run's envs, seeding them and torch with the run's seed
    plus the model's step count: past every seed the run used before (those start at the run's seed,
    and the step count grows by at least ``n_envs`` from one checkpoint to the next)."""
    model.set_env(env)
    model.set_random_seed(run.seed + model.num_timesteps)


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


def make_run_env(
    env_id: str | Callable[..., gym.Env],
    n_envs: int,
    seed: int,
    env_kwargs: dict[str, Any],
    run_dir: Path,
    append: bool = False,
    subprocesses: bool = False,
) -> VecEnv:
    """The training envs of a run: ``n_envs`` copies of ``env_id`` (an id or a function making the env)
    with ``env_kwargs``, and Monitor files in ``run_dir/monitor``.

    By default stepped in the learner's process: a planner-env step with its action mask takes about
    2 ms, and subprocesses would add two pipe round trips to each (``step``, then ``action_masks()``); on
    a shared 2-core machine the planner stage trained 1.1-1.6 times as fast without them
    (docs/experiments/2026-11-26-planner-stage-speed.md). The decider stage, whose step runs the frozen
    planner for T_m steps, asks for ``subprocesses``.

    :param append: continue the Monitor files (a resumed run, after
        :func:`~sb3_gccp.training.checkpoints.rewind_run`): rows are appended, timed from the file's start
    :param subprocesses: one worker process per env (when there is more than one)
    """
    env = make_vec_env(
        env_id,
        n_envs=n_envs,
        seed=seed,
        env_kwargs=env_kwargs,
        monitor_dir=str(run_dir / MONITOR_DIR),
        monitor_kwargs={"override_existing": not append},
        vec_env_cls=SubprocVecEnv if subprocesses and n_envs > 1 else DummyVecEnv,
    )
    if append:
        for name, t_start in monitor_start_times(run_dir).items():
            env.set_attr("t_start", t_start, indices=[int(name.split(".")[0])])
    return env


@contextlib.contextmanager
def removed_if_setup_fails(run: Run) -> Iterator[None]:
    """Take a new run's folder away again when setting the run up fails (settings that only the envs or
    the model reject), so that no half-made run is left for ``latest_run`` or ``--resume``; a resumed
    run's folder stays as it is."""
    try:
        yield
    except BaseException:
        if not run.resumed:
            shutil.rmtree(run.dir, ignore_errors=True)
        raise


def prepare_run_folder(
    run: Run, request: StageRequest, checkpoint: Checkpoint | None, files: Mapping[str, Writer] | None = None
) -> None:
    """Make a new run's folder, or bring a resumed one back to ``checkpoint``, recording its options and
    command line.

    A new folder gets ``files`` (name -> writer), the arguments and options, the command line, and the
    resolved settings last: a folder with ``config.yml`` is a complete run folder (``latest_run``).
    """
    if not run.resumed:
        run.dir.mkdir(parents=True, exist_ok=False)
        for name, write in (files or {}).items():
            write_atomically(run.dir / name, write)
        args = {
            "config_file": str(request.config_file),
            "seed": request.seed,
            "n_timesteps": request.n_timesteps,
            "log_folder": str(request.log_folder),
            "planner": None if request.planner is None else str(request.planner),
            **run.options.to_dict(),
        }
        _write_text(run.dir / ARGS_FILE, yaml.safe_dump(args, sort_keys=True))
        _write_text(run.dir / COMMAND_FILE, shlex.join(request.argv) + "\n")
        _write_text(run.dir / CONFIG_FILE, yaml.safe_dump(run.settings, sort_keys=True))
        return
    rewind_run(run.dir, checkpoint)
    args = yaml.safe_load((run.dir / ARGS_FILE).read_text())
    if any(args.get(k) != v for k, v in run.options.to_dict().items()):
        _write_text(run.dir / ARGS_FILE, yaml.safe_dump({**args, **run.options.to_dict()}, sort_keys=True))
    commands = (run.dir / COMMAND_FILE).read_text() if (run.dir / COMMAND_FILE).is_file() else ""
    _write_text(run.dir / COMMAND_FILE, commands + shlex.join(request.argv) + "\n")


def _write_text(path: Path, text: str) -> None:
    write_atomically(path, lambda temporary: temporary.write_text(text))
