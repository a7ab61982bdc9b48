"""The ``sb3_gccp`` command line.

Commands:

- ``sb3_gccp rollout``: play seeded episodes with the scripted hierarchy (farthest-subgoal
  decision-maker + pure-pursuit motion-planner) and print the paper's table; optional GIF of one episode.
- ``sb3_gccp config``: print every world config key with its value and meaning.
- ``sb3_gccp train --stage planner|decider|predictor|all``: train a stage from a zoo-style YAML file
  (``all``: the planner, then the decision-maker with GCCP on the side).
- ``sb3_gccp evaluate``: run a trained hierarchy (or a flat baseline) on seeded traffic and print the
  paper's table.
- ``sb3_gccp export``: copy a trained run into a small folder that evaluates on its own.
- ``sb3_gccp video``: write a GIF or MP4 of one episode of a trained hierarchy, every 0.1 s step with
  the subgoal candidates, the GCCP mask, the chosen subgoal and the predicted trajectories.
- ``sb3_gccp reproduce --preset quick|paper``: train every method of the paper's Tables I and II on the
  same episode budget, evaluate them on the same traffic flows, write the tables and Figs. 5-8.

Errors in the input are reported on one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import itertools
import json
import sys
from pathlib import Path
from typing import Any

import yaml

from gccp_envs.config import DT, TASKS, IntersectionConfig


class CLIError(Exception):
    """A problem with the command's input, reported on one line."""


def load_world_config(path: str | None, assignments: list[str]) -> IntersectionConfig:
    """The world config from an optional YAML file of config keys plus ``KEY=VALUE`` overrides.

    Values of ``--set`` are read as YAML scalars or lists (``task=left``, ``spawn_probability=0.1``).
    """
    from sb3_gccp.hyperparams import HyperparamsError, read_yaml_mapping

    values: dict[str, Any] = {}
    if path is not None:
        try:
            values.update(read_yaml_mapping(path, "config file"))
        except HyperparamsError as err:
            raise CLIError(str(err)) from err
    values.update(parse_assignments(assignments))
    try:
        return IntersectionConfig.from_dict(values)
    except (ValueError, TypeError) as err:
        raise CLIError(str(err)) from err


def parse_assignments(assignments: list[str], flag: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` strings (of option ``flag``) as a mapping, values read as YAML scalars or lists."""
    values: dict[str, Any] = {}
    for item in assignments:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise CLIError(f"{flag} expects KEY=VALUE, got {item!r}")
        values[key.strip()] = yaml.safe_load(raw)
    return values


def parse_tasks(text: str) -> list[str]:
    """Comma-separated task names, validated."""
    tasks = [t.strip() for t in text.split(",") if t.strip()]
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise CLIError(
            f"unknown task(s) {', '.join(map(repr, unknown)) or '(none)'}: expected a "
            f"comma-separated subset of {','.join(TASKS)}"
        )
    return tasks


def _rollout(args: argparse.Namespace) -> None:
    from gccp_envs.option_env import GCCPDeciderEnv
    from gccp_envs.scripted import FarthestSubgoalDecider
    from sb3_gccp.evaluation import evaluate, format_table, run_episode, summarize

    config = load_world_config(args.config, args.set)
    tasks = parse_tasks(args.tasks)
    if args.episodes_per_task < 1:
        raise CLIError("--episodes-per-task must be at least 1")
    env = GCCPDeciderEnv(config)
    decider = FarthestSubgoalDecider()
    results = evaluate(env, decider, tasks, args.episodes_per_task, args.seed, progress=not args.no_progress)
    table = summarize(results)
    print(f"scripted hierarchy, {args.episodes_per_task} episodes per task from seed {args.seed}")
    print(format_table(table))
    if args.json:
        Path(args.json).write_text(
            json.dumps({"table": table, "episodes": [dataclasses.asdict(r) for r in results]}, indent=2)
        )
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


def _train(args: argparse.Namespace) -> None:
    from sb3_gccp.decider_stage import train_all, train_decider
    from sb3_gccp.hyperparams import HyperparamsError, default_config_file
    from sb3_gccp.stages import StageRequest, latest_run, train_planner

    if args.stage == "predictor":
        _train_predictor(args)
        return
    if args.stage == "decider" and args.resume is None and not args.planner:
        raise CLIError("the decider stage needs --planner PATH.zip (a trained motion-planner)")
    if args.stage == "all" and args.resume is not None:
        raise CLIError("--resume works per stage: use --stage planner or --stage decider with --resume")
    config_file = Path(args.config) if args.config else default_config_file("ppo_mask.yml")
    resume = None
    if args.resume is not None:
        resume = Path(args.resume) if args.resume else latest_run(Path(args.log_folder) / args.stage)
        if resume is None:
            raise CLIError(f"nothing to resume in {Path(args.log_folder) / args.stage}")
    if args.n_timesteps is not None and args.n_timesteps < 1:
        raise CLIError("-n/--n-timesteps must be positive")
    request = StageRequest(
        config_file=config_file,
        seed=args.seed,
        n_timesteps=args.n_timesteps,
        log_folder=Path(args.log_folder),
        resume=resume,
        progress_bar=not args.no_progress,
        verbose=args.verbose,
        save_freq=args.save_freq,
        torch_threads=args.torch_threads,
        planner=Path(args.planner) if args.planner else None,
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    try:
        if args.stage == "planner":
            print(f"saved {train_planner(request)}")
        elif args.stage == "decider":
            print(f"saved {train_decider(request)}")
        else:
            planner, run_dir = train_all(request)
            print(f"saved {planner}")
            print(f"saved {run_dir}")
    except (HyperparamsError, ValueError, OSError) as err:
        raise CLIError(str(err)) from err


def _evaluate(args: argparse.Namespace) -> None:
    from sb3_gccp.evaluation import evaluate, format_table, summarize

    tasks = parse_tasks(args.tasks)
    if args.episodes_per_task < 1:
        raise CLIError("--episodes-per-task must be at least 1")
    try:
        env, decider, what = _evaluation_target(args)
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    if args.stochastic:
        import torch as th

        th.manual_seed(args.seed)
    results = evaluate(env, decider, tasks, args.episodes_per_task, args.seed, progress=not args.no_progress)
    table = summarize(results)
    print(
        f"{what}, {args.episodes_per_task} episodes per task from seed {args.seed}"
        + (", stochastic decisions" if args.stochastic else "")
    )
    print(format_table(table))
    if args.json:
        Path(args.json).write_text(
            json.dumps({"table": table, "episodes": [dataclasses.asdict(r) for r in results]}, indent=2)
        )


def _evaluation_target(args: argparse.Namespace) -> tuple[Any, Any, str]:
    """The env, the policy and a description of ``--model``: a hierarchy or a flat baseline run."""
    from sb3_gccp.baselines import BASELINE_FILE, load_baseline
    from sb3_gccp.hierarchy import load_hierarchy

    model = Path(args.model)
    folder = model.parent if model.is_file() else model
    overrides = parse_assignments(args.set)
    if (folder / BASELINE_FILE).is_file():
        if args.stochastic:
            raise CLIError("--stochastic: baselines are evaluated with their most likely action only")
        if args.mask:
            raise CLIError("--mask: baselines have no GCCP check")
        env, policy, name = load_baseline(folder, overrides)
        return env, policy, f"baseline {name} {args.model}"
    mask = parse_assignments(args.mask, "--mask")
    hierarchy = load_hierarchy(args.model, mask, args.allow_overrides)
    decider = hierarchy.decider_policy(deterministic=not args.stochastic)
    check = "".join(f", {key}={value}" for key, value in mask.items())
    return (
        hierarchy.make_env(overrides),
        decider,
        f"hierarchy {args.model} (GCCP: {hierarchy.predictor}{check})",
    )


def _export(args: argparse.Namespace) -> None:
    from sb3_gccp.export import export_run

    try:
        written = export_run(
            args.run, args.out, parse_assignments(args.set), parse_assignments(args.mask, "--mask")
        )
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    size = sum(path.stat().st_size for path in written)
    print(f"exported {args.run} to {args.out}: {len(written)} files, {size / 1e6:.1f} MB")


def _video(args: argparse.Namespace) -> None:
    from sb3_gccp.hierarchy import load_hierarchy
    from sb3_gccp.video import check_video_path, record_episode, write_video

    if args.task not in TASKS:
        raise CLIError(f"unknown task {args.task!r}: expected one of {', '.join(TASKS)}")
    if args.max_steps is not None and args.max_steps < 1:
        raise CLIError("--max-steps must be at least 1")
    if args.fps <= 0:
        raise CLIError("--fps must be positive")
    try:
        check_video_path(args.out)
        hierarchy = load_hierarchy(args.model, parse_assignments(args.mask, "--mask"), args.allow_overrides)
        env = hierarchy.make_env(parse_assignments(args.set))
        decider = hierarchy.decider_policy()
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


def _reproduce(args: argparse.Namespace) -> None:
    from sb3_gccp.reproduce import METHODS, ReproduceRequest, prepare, reproduce

    request = ReproduceRequest(
        preset=args.preset,
        overrides=parse_assignments(args.set),
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


def _train_predictor(args: argparse.Namespace) -> None:
    from dataclasses import asdict

    from sb3_gccp.predictor_stage import PredictorRequest, train_predictor_stage

    world = asdict(load_world_config(None, args.set))
    request = PredictorRequest(
        planner=Path(args.planner) if args.planner else None,
        buffer=Path(args.buffer) if args.buffer else None,
        subgoals=args.subgoals,
        episodes=args.episodes,
        heldout_episodes=args.heldout_episodes,
        gradient_steps=args.gradient_steps,
        eval_every=args.eval_every,
        seed=args.seed,
        log_folder=Path(args.log_folder),
        progress_bar=not args.no_progress,
        torch_threads=args.torch_threads,
        world=world,
        predictor_kwargs=parse_assignments(args.predictor_set, "--predictor-set"),
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    try:
        run_dir = train_predictor_stage(request)
    except (ValueError, OSError) as err:
        raise CLIError(str(err)) from err
    print(f"saved {run_dir}")


def _config(args: argparse.Namespace) -> None:
    config = load_world_config(args.config, args.set)
    docs = _field_docs()
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        shown = list(value) if isinstance(value, tuple) else value
        print(f"{field.name}: {json.dumps(shown)}  # {docs.get(field.name, '')}")


def _field_docs() -> dict[str, str]:
    """The one-line docstring under each config field, read from the source."""
    import inspect

    tree = ast.parse(inspect.getsource(IntersectionConfig))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, following in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(node.target, ast.Name)
        ):
            docs[node.target.id] = " ".join(str(following.value.value).split())
    return docs


def add_world_overrides(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--set KEY=VALUE`` (repeatable): world config keys replacing a trained model's."""
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a world config key (repeatable)",
    )


def add_mask_overrides(parser: argparse.ArgumentParser) -> None:
    """``--mask KEY=VALUE`` (repeatable): GCCP check settings replacing a trained hierarchy's."""
    parser.add_argument(
        "--mask",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a GCCP check setting of hierarchy.yml (repeatable): mask_margin, "
        "mask_extrapolate_steps, mask_ego_deceleration, mask_yield_margin",
    )


def add_allow_overrides(parser: argparse.ArgumentParser) -> None:
    """``--allow-overrides``: run a hierarchy whose ``hierarchy.yml`` has an ``overrides`` section."""
    parser.add_argument(
        "--allow-overrides",
        action="store_true",
        help="run the overrides section of hierarchy.yml (settings the decider was not trained with)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``sb3_gccp``."""
    parser = argparse.ArgumentParser(prog="sb3_gccp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def world_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--config", help="YAML file of world config keys (see `sb3_gccp config`)")
        add_world_overrides(p)

    rollout = sub.add_parser("rollout", help="play seeded episodes with the scripted hierarchy")
    rollout.add_argument("--tasks", default=",".join(TASKS), help="comma-separated: left,straight,right")
    rollout.add_argument("--episodes-per-task", type=int, default=20)
    rollout.add_argument("--seed", type=int, default=0, help="first traffic seed")
    rollout.add_argument("--json", help="also write the table and every episode to this JSON file")
    rollout.add_argument("--gif", help="also write a GIF of the first task's first episode")
    rollout.add_argument("--no-progress", action="store_true", help="no progress bar")
    world_options(rollout)
    rollout.set_defaults(func=_rollout)

    train = sub.add_parser("train", help="train a stage from a zoo-style YAML file")
    train.add_argument(
        "--stage",
        choices=["planner", "decider", "predictor", "all"],
        required=True,
        help="planner: MaskablePPO on GCCPPlanner-v0; decider: MaskablePPO on GCCPDecider-v0 with the "
        "frozen --planner and GCCP on the side; predictor: the GCCP trajectory predictor alone; "
        "all: planner then decider",
    )
    train.add_argument("--config", help="zoo-style YAML (default: zoo_configs/ppo_mask.yml)")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("-n", "--n-timesteps", type=int, help="override the file's n_timesteps")
    train.add_argument("--log-folder", default="runs", help="runs go to LOG_FOLDER/STAGE/ENV_SEED_TIME")
    train.add_argument(
        "--resume",
        nargs="?",
        const="",
        metavar="RUN_DIR",
        help="continue a run from its last checkpoint (default: the newest run)",
    )
    train.add_argument("--save-freq", type=int, default=10_000, help="env steps between checkpoints")
    train.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="torch threads of the learner (default 1: the env workers need the other cores, and the "
        "recipe in zoo_configs/ was run with 1)",
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("-v", "--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")
    train.add_argument(
        "--planner",
        help="frozen motion-planner .zip (decider and predictor stages), or 'scripted' (the scripted "
        "pure-pursuit planner)",
    )
    predictor = train.add_argument_group("predictor stage")
    predictor.add_argument("--buffer", help="train on this saved replay buffer (.npz) instead of collecting")
    predictor.add_argument(
        "--subgoals", default="random", help="subgoals while collecting: random, farthest or a decider .zip"
    )
    predictor.add_argument("--episodes", type=int, default=200, help="training episodes to collect")
    predictor.add_argument("--heldout-episodes", type=int, default=50, help="held-out episodes to collect")
    predictor.add_argument("--gradient-steps", type=int, default=3000, help="predictor gradient steps")
    predictor.add_argument("--eval-every", type=int, default=250, help="gradient steps between evaluations")
    predictor.add_argument(
        "--predictor-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="PredictorConfig field of both learned predictors (repeatable): cv_residual=true",
    )
    add_world_overrides(predictor)
    train.set_defaults(func=_train)

    evaluate = sub.add_parser(
        "evaluate", help="run a trained hierarchy (or a flat baseline) on seeded traffic flows"
    )
    evaluate.add_argument(
        "--model",
        required=True,
        help="a decider run folder, pretrained/, a decider .zip inside one, or a baseline run folder "
        "(baseline.yml)",
    )
    evaluate.add_argument("--tasks", default=",".join(TASKS), help="comma-separated: left,straight,right")
    evaluate.add_argument("--episodes-per-task", type=int, default=50)
    evaluate.add_argument("--seed", type=int, default=0, help="first traffic seed")
    evaluate.add_argument("--json", help="also write the table and every episode to this JSON file")
    evaluate.add_argument(
        "--stochastic",
        action="store_true",
        help="sample subgoals from the decision-maker's policy (seeded by --seed) instead of its argmax",
    )
    evaluate.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_world_overrides(evaluate)
    add_mask_overrides(evaluate)
    add_allow_overrides(evaluate)
    evaluate.set_defaults(func=_evaluate)

    video = sub.add_parser("video", help="write a GIF or MP4 of one episode of a trained hierarchy")
    video.add_argument(
        "--model", required=True, help="a decider run folder, pretrained/, or a decider .zip inside one"
    )
    video.add_argument("--task", default="left", help="left, straight or right")
    video.add_argument("--seed", type=int, default=0, help="traffic seed")
    video.add_argument("--out", required=True, help="the video file: .gif, or .mp4 (needs imageio-ffmpeg)")
    video.add_argument(
        "--max-steps", type=int, help="stop after this many 0.1 s steps (default: the episode)"
    )
    video.add_argument("--fps", type=float, default=10.0, help="frames per second (10: real time)")
    add_world_overrides(video)
    add_mask_overrides(video)
    add_allow_overrides(video)
    video.set_defaults(func=_video)

    reproduce = sub.add_parser(
        "reproduce", help="train and evaluate every method of the paper's Tables I and II; tables, figures"
    )
    reproduce.add_argument(
        "--preset",
        default="paper",
        help="budgets: quick (the whole pipeline in minutes) or paper (the paper's, hours per seed)",
    )
    reproduce.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds (default: 0)")
    reproduce.add_argument(
        "--methods",
        nargs="+",
        help="a subset of: ours with_cv without_gccp without_goal dqn ppo sac_discrete (default: all)",
    )
    reproduce.add_argument(
        "--planner",
        help="motion-planner .zip, or 'scripted', for every hierarchy variant (default: train one per seed)",
    )
    reproduce.add_argument("--out", default="results", help="tables, CSV/JSON, figures and configs go here")
    reproduce.add_argument(
        "--log-folder", default="runs", help="runs go to LOG_FOLDER/reproduce/PRESET/seedK/METHOD"
    )
    reproduce.add_argument("--eval-seed", type=int, default=0, help="first traffic seed of the evaluation")
    reproduce.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="torch threads of the learners (default 1: the networks are small, and more threads slow "
        "them down on a busy machine)",
    )
    reproduce.add_argument("--no-progress", action="store_true", help="no progress bars")
    reproduce.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a preset field (repeatable); dotted for maps: --set episodes=100 "
        "--set world.duration=20 --set hyperparams.dqn.buffer_size=10000",
    )
    reproduce.set_defaults(func=_reproduce)

    export = sub.add_parser(
        "export", help="copy a trained run into a small folder that evaluates on its own (like pretrained/)"
    )
    export.add_argument("run", help="a decider run folder (hierarchy.yml) or a baseline run folder")
    export.add_argument("out", help="a new (or empty) folder")
    add_world_overrides(export)
    add_mask_overrides(export)
    export.set_defaults(func=_export)

    config = sub.add_parser("config", help="print the world config keys, values and meanings")
    world_options(config)
    config.set_defaults(func=_config)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``sb3_gccp``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except CLIError as err:
        print(f"sb3_gccp: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sb3_gccp: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
