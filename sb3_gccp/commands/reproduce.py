"""``sb3_gccp reproduce --preset quick|paper``: train every method of the paper's Tables I and II on the
same episode budget, evaluate them on the same traffic flows, write the tables and Figs. 5-8."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sb3_gccp.commands.common import CLIError, add_torch_threads, parse_assignments


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
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds (default: 0)")
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
    parser.add_argument("--eval-seed", type=int, default=0, help="first traffic seed of the evaluation")
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
    from sb3_gccp.reproduce.methods import METHODS
    from sb3_gccp.reproduce.plan import ReproduceRequest, prepare
    from sb3_gccp.reproduce.runner import reproduce

    request = ReproduceRequest(
        preset=args.preset,
        overrides=parse_assignments(args.set),
        zoo_files=parse_zoo_files(args.config),
        seeds=tuple(args.seeds),
        methods=tuple(args.methods or METHODS),
        planner=Path(args.planner) if args.planner else None,
        out=Path(args.out),
        log_folder=Path(args.log_folder),
        eval_seed=args.eval_seed,
        torch_threads=args.torch_threads,
        progress_bar=not args.no_progress,
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    try:
        plan = prepare(request)
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    try:
        results = reproduce(plan)
    except (ValueError, OSError) as err:  # HyperparamsError included
        raise CLIError(str(err)) from err
    print(
        f"done in {results['wall_clock_s']:.0f} s: {request.out}/table1.md, table2.md, results.json, figures"
    )


def parse_zoo_files(items: list[str]) -> dict[str, Path]:
    """``--config METHOD=FILE`` options as a map of method to zoo file."""
    files = {}
    for item in items:
        method, sep, file = item.partition("=")
        if not sep or not method or not file:
            raise CLIError(f"--config expects METHOD=FILE, got {item!r}")
        files[method.strip()] = Path(file)
    return files
