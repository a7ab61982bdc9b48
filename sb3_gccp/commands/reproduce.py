"""``sb3_gccp reproduce --preset quick|paper``: train every method of the paper's Tables I and II on the
same episode budget, evaluate them on the same traffic flows, write the tables and Figs. 5-8."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from sb3_gccp.commands.common import CLIError, add_torch_threads, parse_assignments, seed_value


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser(
        "reproduce", help="train and evaluate every method of the paper's Tables I and II; tables, figures"
    )
    parser.add_argument(
        "--preset",
        default="paper",
        help="budgets: quick (the whole pipeline in minutes) or paper (the paper's, hours per seed)",
    )
    parser.add_argument(
        "--seeds", type=seed_value, nargs="+", default=[0], help="training seeds (default: 0)"
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        help="a subset of: ours with_cv without_gccp without_goal dqn ppo sac_discrete (default: all)",
    )
    parser.add_argument(
        "--planner",
        help="motion-planner .zip, or 'scripted', for every hierarchy variant (default: train one per seed)",
    )
    parser.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="METHOD=FILE",
        help="a method's zoo file in place of the shipped entry (repeatable), such as the best.yml of "
        "`sb3_gccp tune`: --config ppo=tune/ppo/best.yml (a hierarchy variant takes its GCCPDecider-v0 "
        "entry)",
    )
    parser.add_argument("--out", default="results", help="tables, CSV/JSON, figures and configs go here")
    parser.add_argument(
        "--log-folder", default="runs", help="runs go to LOG_FOLDER/reproduce/PRESET/seedK/METHOD"
    )
    parser.add_argument(
        "--eval-seed", type=seed_value, default=0, help="first traffic seed of the evaluation"
    )
    parser.add_argument(
        "--jobs",
        type=int,
        help="runs at once, each (method, seed) run a job after the jobs it needs (default: 1 here, one "
        "after another; every ready job with --launcher submitit)",
    )
    parser.add_argument(
        "--launcher",
        default="local",
        choices=("local", "submitit"),
        help="local: here (N processes with --jobs N); submitit: each job through submitit's AutoExecutor "
        "(Slurm where sbatch is, else its local executor), logs in LOG_FOLDER/reproduce/PRESET/submitit",
    )
    parser.add_argument(
        "--launcher-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a submitit parameter (repeatable): --launcher-set timeout_min=600 "
        "--launcher-set slurm_partition=gpu (default timeout_min: 1440)",
    )
    parser.add_argument(
        "--collect",
        metavar="OUT",
        help="train nothing: write the tables, data and figures into OUT from the finished runs of the "
        "same --preset, --seeds, --methods, --planner and --log-folder (the preset is read from there)",
    )
    add_torch_threads(parser, "the learners")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a preset field (repeatable); dotted for maps: --set episodes=100 "
        "--set world.duration=20 --set hyperparams.dqn.buffer_size=10000",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Check the request, run the reproduction and say where its outputs went."""
    import torch as th

    from sb3_gccp.reproduce.collect import collect
    from sb3_gccp.reproduce.launchers import JobFailed, check_launcher, make_launcher, reproduce
    from sb3_gccp.reproduce.methods import METHODS
    from sb3_gccp.reproduce.plan import ReproduceRequest, prepare

    request = ReproduceRequest(
        preset=args.preset,
        overrides=parse_assignments(args.set),
        zoo_files=parse_zoo_files(args.config),
        seeds=tuple(args.seeds),
        methods=tuple(args.methods or METHODS),
        planner=Path(args.planner) if args.planner else None,
        out=Path(args.collect or args.out),
        log_folder=Path(args.log_folder),
        eval_seed=args.eval_seed,
        torch_threads=args.torch_threads,
        progress_bar=not args.no_progress,
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    launcher_set = parse_assignments(args.launcher_set, "--launcher-set")
    try:
        check_launcher(args.launcher, args.jobs, launcher_set)
        plan = prepare(request, collect=args.collect is not None)
        launcher = None if args.collect else make_launcher(plan, args.launcher, args.jobs, launcher_set)
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    signal.signal(signal.SIGTERM, _interrupt)  # a killed reproduce stops its jobs as Ctrl-C does
    if request.torch_threads is not None:  # the evaluations and figures made here; each job sets its own
        th.set_num_threads(request.torch_threads)
    try:
        results = collect(plan) if args.collect else reproduce(plan, launcher)
    except (ValueError, OSError, JobFailed) as err:  # HyperparamsError included
        raise CLIError(str(err)) from err
    # Only the tables with a method in them are written (each named above as it is).
    print(f"done in {results['wall_clock_s']:.0f} s: tables, results.json and figures in {request.out}")


def parse_zoo_files(items: list[str]) -> dict[str, Path]:
    """``--config METHOD=FILE`` options as a map of method to zoo file."""
    files = {}
    for item in items:
        method, sep, file = item.partition("=")
        if not sep or not method or not file:
            raise CLIError(f"--config expects METHOD=FILE, got {item!r}")
        files[method.strip()] = Path(file)
    return files


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt
