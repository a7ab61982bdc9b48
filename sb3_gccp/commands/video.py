"""``sb3_gccp video``: a GIF or MP4 of one episode of a trained hierarchy, every 0.1 s step with the
subgoal candidates, the GCCP mask, the chosen subgoal and the predicted trajectories."""

from __future__ import annotations

import argparse

from gccp_envs.config import DT, TASKS
from sb3_gccp.commands.common import (
    CLIError,
    add_allow_overrides,
    add_mask_overrides,
    add_trust_pickle,
    add_world_overrides,
    parse_assignments,
    seed_value,
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser("video", help="write a GIF or MP4 of one episode of a trained hierarchy")
    parser.add_argument(
        "--model", required=True, help="a decider run folder, pretrained/, or a decider .zip inside one"
    )
    parser.add_argument("--task", default="left", help="left, straight or right")
    parser.add_argument("--seed", type=seed_value, default=0, help="traffic seed")
    parser.add_argument("--out", required=True, help="the video file: .gif, or .mp4 (needs imageio-ffmpeg)")
    parser.add_argument(
        "--max-steps", type=int, help="stop after this many 0.1 s steps (default: the episode)"
    )
    parser.add_argument("--fps", type=float, default=10.0, help="frames per second (10: real time)")
    add_world_overrides(parser)
    add_mask_overrides(parser)
    add_allow_overrides(parser)
    add_trust_pickle(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Record the episode, write the video and say how the episode ended."""
    import torch as th

    from sb3_gccp.hierarchy import load_hierarchy
    from sb3_gccp.video import check_video_path, record_episode, write_video

    if args.task not in TASKS:
        raise CLIError(f"unknown task {args.task!r}: expected one of {', '.join(TASKS)}")
    if args.max_steps is not None and args.max_steps < 1:
        raise CLIError("--max-steps must be at least 1")
    if not 0 < args.fps <= 1000:
        raise CLIError(f"--fps must be a number in (0, 1000], got {args.fps:g}")
    th.set_num_threads(1)  # the networks are small: more threads only add overhead
    try:
        check_video_path(args.out)
        hierarchy = load_hierarchy(args.model, parse_assignments(args.mask, "--mask"), args.allow_overrides)
        env = hierarchy.make_env(parse_assignments(args.set), trusted=args.trust_pickle)
        decider = hierarchy.decider_policy(env.config, trusted=args.trust_pickle)
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    recording = record_episode(env, decider, args.task, args.seed, args.max_steps)
    try:
        write_video(recording.frames, args.out, args.fps)
    except (ValueError, OSError) as err:
        raise CLIError(str(err)) from err
    print(f"wrote {args.out} ({len(recording.frames)} frames at {args.fps:g} fps)")
    print(
        f"hierarchy {args.model} (GCCP: {hierarchy.predictor}), task {args.task}, seed {args.seed}: "
        f"{recording.outcome} after {recording.steps} steps "
        f"({recording.steps * DT:.1f} s, {recording.decisions} decisions)"
    )
