"""``sb3_gccp evaluate``: a trained hierarchy (or a flat baseline) on seeded traffic, in the paper's table."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gccp_envs.config import TASKS
from sb3_gccp.commands.common import (
    CLIError,
    add_allow_overrides,
    add_mask_overrides,
    add_trust_pickle,
    add_world_overrides,
    check_output_path,
    parse_assignments,
    parse_tasks,
    seed_value,
    write_results,
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser(
        "evaluate", help="run a trained hierarchy (or a flat baseline) on seeded traffic flows"
    )
    parser.add_argument(
        "--model",
        required=True,
        help="a decider run folder, pretrained/, a decider .zip inside one, or a baseline run folder "
        "(baseline.yml)",
    )
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated: left,straight,right")
    parser.add_argument("--episodes-per-task", type=int, default=50)
    parser.add_argument("--seed", type=seed_value, default=0, help="first traffic seed")
    parser.add_argument("--json", help="also write the table and every episode to this JSON file")
    parser.add_argument(
        "--stochastic",
        action="store_true",
        help="sample subgoals from the decision-maker's policy (seeded by --seed) instead of its argmax",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_world_overrides(parser)
    add_mask_overrides(parser)
    add_allow_overrides(parser)
    add_trust_pickle(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Evaluate the model, print the table and write the JSON asked for."""
    import torch as th

    from sb3_gccp.evaluation import evaluate, format_table, summarize

    tasks = parse_tasks(args.tasks)
    if args.episodes_per_task < 1:
        raise CLIError("--episodes-per-task must be at least 1")
    check_output_path(args.json, "--json")
    th.set_num_threads(1)  # the networks are small: more threads only add overhead
    try:
        env, decider, what = _evaluation_target(args)
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    if args.stochastic:
        th.manual_seed(args.seed)
    results = evaluate(env, decider, tasks, args.episodes_per_task, args.seed, progress=not args.no_progress)
    table = summarize(results)
    print(
        f"{what}, {args.episodes_per_task} episodes per task from seed {args.seed}"
        + (", stochastic decisions" if args.stochastic else "")
    )
    print(format_table(table))
    if args.json:
        write_results(args.json, table, results)


def _evaluation_target(args: argparse.Namespace) -> tuple[Any, Any, str]:
    """The env, the policy and a description of ``--model``: a hierarchy or a flat baseline run."""
    from sb3_gccp.constants import BASELINE_FILE
    from sb3_gccp.hierarchy import load_hierarchy
    from sb3_gccp.training.baselines import load_baseline

    model = Path(args.model)
    folder = model.parent if model.is_file() else model
    overrides = parse_assignments(args.set)
    if (folder / BASELINE_FILE).is_file():
        if args.stochastic:
            raise CLIError("--stochastic: baselines are evaluated with their most likely action only")
        if args.mask:
            raise CLIError("--mask: baselines have no GCCP check")
        env, policy, name = load_baseline(folder, overrides, args.trust_pickle)
        return env, policy, f"baseline {name} {args.model}"
    mask = parse_assignments(args.mask, "--mask")
    hierarchy = load_hierarchy(args.model, mask, args.allow_overrides)
    env = hierarchy.make_env(overrides, trusted=args.trust_pickle)
    decider = hierarchy.decider_policy(env.config, not args.stochastic, args.trust_pickle)
    check = "".join(f", {key}={value}" for key, value in mask.items())
    return env, decider, f"hierarchy {args.model} (GCCP: {hierarchy.predictor}{check})"
