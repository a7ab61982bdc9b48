"""``sb3_gccp rollout``: seeded episodes of the scripted hierarchy (farthest-subgoal decision-maker over
the pure-pursuit motion-planner) and the paper's table; optionally a GIF of one episode."""

from __future__ import annotations

import argparse
from typing import Any

from gccp_envs.config import TASKS
from sb3_gccp.commands.common import (
    CLIError,
    add_world_options,
    check_output_path,
    load_world_config,
    parse_tasks,
    seed_value,
    write_results,
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser("rollout", help="play seeded episodes with the scripted hierarchy")
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated: left,straight,right")
    parser.add_argument("--episodes-per-task", type=int, default=20)
    parser.add_argument("--seed", type=seed_value, default=0, help="first traffic seed")
    parser.add_argument("--json", help="also write the table and every episode to this JSON file")
    parser.add_argument("--gif", help="also write a GIF of the first task's first episode")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_world_options(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Play the episodes, print the table, write the JSON and GIF asked for."""
    from gccp_envs.option_env import GCCPDeciderEnv
    from gccp_envs.scripted import FarthestSubgoalDecider
    from sb3_gccp.evaluation import evaluate, format_table, run_episode, summarize

    config = load_world_config(args.config, args.set)
    tasks = parse_tasks(args.tasks)
    if args.episodes_per_task < 1:
        raise CLIError("--episodes-per-task must be at least 1")
    check_output_path(args.json, "--json")
    check_output_path(args.gif, "--gif")
    if args.gif is not None and not args.gif.lower().endswith(".gif"):
        raise CLIError(f"--gif {args.gif}: the file name must end in .gif")
    env = GCCPDeciderEnv(config)
    decider = FarthestSubgoalDecider()
    results = evaluate(env, decider, tasks, args.episodes_per_task, args.seed, progress=not args.no_progress)
    table = summarize(results)
    print(f"scripted hierarchy, {args.episodes_per_task} episodes per task from seed {args.seed}")
    print(format_table(table))
    if args.json:
        write_results(args.json, table, results)
    if args.gif:
        _write_gif(
            GCCPDeciderEnv(config, render_mode="rgb_array"),
            decider,
            tasks[0],
            args.seed,
            args.gif,
            run_episode,
        )


def _write_gif(env: Any, policy: Any, task: str, seed: int, path: str, run_episode: Any) -> None:
    from PIL import Image

    frames: list[Any] = []
    run_episode(env, policy, task, seed, on_step=lambda e: frames.append(Image.fromarray(e.render())))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=500, loop=0)
    print(f"wrote {path} ({len(frames)} frames, one per decision)")
