"""``sb3_gccp tune --method dqn|ppo|sac_discrete|decider``: search a method's hyperparameters with Optuna,
a fixed episode budget per trial; write the best trial as a zoo entry."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from sb3_gccp.commands.common import CLIError, add_torch_threads, seed_value
from sb3_gccp.constants import SCRIPTED

if TYPE_CHECKING:
    from sb3_gccp.tune.study import Study

METHODS = ("dqn", "ppo", "sac_discrete", "decider")
"""The methods ``--method`` takes (:data:`sb3_gccp.tune.objective.TUNE_METHODS`)."""


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser(
        "tune", help="search a method's hyperparameters with Optuna; the best trial as a zoo entry"
    )
    parser.add_argument("--method", choices=METHODS, required=True)
    parser.add_argument(
        "--n-trials",
        type=int,
        default=20,
        help="finished (complete or pruned) trials the study should hold, over every process that joins "
        "it (default 20); run the command again to resume, with a larger N to add trials",
    )
    parser.add_argument(
        "--episodes-per-trial", type=int, required=True, help="training episodes of every trial"
    )
    parser.add_argument(
        "--storage",
        help="Optuna storage: an SQLAlchemy URL (sqlite:///t.db, postgresql://..., mysql://...) or "
        "journal://PATH for a journal file on a shared disk (default: sqlite in OUT/study.db)",
    )
    parser.add_argument("--study-name", help="the study to create or join (default: the method's name)")
    parser.add_argument(
        "--n-jobs",
        type=int,
        default=1,
        help="worker processes on this machine, sharing the study (default 1)",
    )
    parser.add_argument("--space", help="search-space YAML (default: zoo_configs/tune/METHOD.yml)")
    parser.add_argument(
        "--config",
        help="zoo file whose entry trials start from (default: the shipped one, zoo_configs/METHOD.yml or "
        "ppo_mask.yml for the decider)",
    )
    parser.add_argument("--seed", type=seed_value, default=0, help="training seed of every trial (default 0)")
    parser.add_argument("--out", default="tune", help="storage, trial run folders and best.yml go here")
    parser.add_argument(
        "--planner",
        help="the decider's frozen motion-planner .zip, or 'scripted' (default: pretrained/planner.zip)",
    )
    add_torch_threads(parser, "every worker")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Check the request, run the study and say where the best entry went."""
    from sb3_gccp.hyperparams import HyperparamsError

    study = prepare(args)
    from sb3_gccp.tune.study import display_url, run_study, write_best_entry

    try:
        optuna_study = run_study(study)
        best = write_best_entry(study, optuna_study)
    except (HyperparamsError, RuntimeError) as err:
        raise CLIError(str(err)) from err
    where = f"study {study.name!r} in {display_url(study.storage_url)}"
    if best is None:
        print(f"{where}: no trial completed, no best entry")
        return
    best_trial = optuna_study.best_trial
    print(f"{where}: best rolling success {best_trial.value:.3f} (trial {best_trial.number})")
    print(f"saved {best}")


def prepare(args: argparse.Namespace) -> Study:
    """The study the arguments ask for, every input checked before any trial.

    :raises CLIError: one line naming what is wrong
    """
    from sb3_gccp.hyperparams import HyperparamsError, default_config_file

    try:
        import optuna
    except ImportError as err:
        raise CLIError('sb3_gccp tune needs Optuna: pip install -e ".[tune]"') from err
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # the progress bar and our lines say enough
    from sb3_gccp.tune.objective import TUNE_METHODS, TrialSettings
    from sb3_gccp.tune.space import SearchSpace
    from sb3_gccp.tune.study import STORAGE_FILE, Study, open_study

    for flag, value in (("--n-trials", args.n_trials), ("--episodes-per-trial", args.episodes_per_trial)):
        if value < 1:
            raise CLIError(f"{flag} must be at least 1, got {value}")
    if args.n_jobs < 1 or args.torch_threads < 1:
        raise CLIError("--n-jobs and --torch-threads must be at least 1")
    method = TUNE_METHODS[args.method]
    planner = None
    if method.name == "decider":
        planner = Path(args.planner) if args.planner else default_planner()
        if planner != Path(SCRIPTED) and not planner.is_file():
            raise CLIError(f"planner not found: {planner} (give --planner PATH.zip or 'scripted')")
    elif args.planner:
        raise CLIError("--planner is the decider's: the baselines drive the flat env themselves")
    out = Path(args.out)
    name = args.study_name or method.name
    made: list[Path] = []
    try:
        entry = method.base_entry(Path(args.config) if args.config else None)
        method.check_entry(entry)
        space_file = Path(args.space) if args.space else default_config_file(f"tune/{method.name}.yml")
        space = SearchSpace.from_file(space_file, lambda key: method.check_key(key, entry))
        method.check_space(space, entry, args.episodes_per_trial)
        made = [folder for folder in (out, out / name) if not folder.exists()]
        out.mkdir(parents=True, exist_ok=True)
        (out / name).mkdir(exist_ok=True)
        trials = TrialSettings(
            method,
            space,
            entry,
            args.episodes_per_trial,
            (out / name).resolve(),
            seed=args.seed,
            torch_threads=args.torch_threads,
            planner=planner.resolve() if planner is not None and planner != Path(SCRIPTED) else planner,
            argv=["sb3_gccp", *sys.argv[1:]],
        )
        storage = args.storage or f"sqlite:///{(out / STORAGE_FILE).resolve()}"
        study = Study(name, storage, args.n_trials, trials, args.n_jobs, not args.no_progress)
        open_study(study)  # a storage that cannot be opened, or a study of other settings, fails here
    except (HyperparamsError, ValueError, TypeError, OSError) as err:
        for folder in made:  # no half-made output folder is left
            shutil.rmtree(folder, ignore_errors=True)
        raise CLIError(str(err)) from err
    return study


def default_planner() -> Path:
    """``pretrained/planner.zip`` of the checkout (the shipped motion-planner)."""
    return Path(__file__).resolve().parents[2] / "pretrained" / "planner.zip"
