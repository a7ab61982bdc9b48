"""``sb3_gccp train --stage planner|decider|predictor|all``: train a stage from a zoo-style YAML file
(``all``: the planner, then the decision-maker with GCCP on the side)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from sb3_gccp.commands.common import (
    CLIError,
    add_torch_threads,
    load_world_config,
    parse_assignments,
    seed_value,
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser("train", help="train a stage from a zoo-style YAML file")
    parser.add_argument(
        "--stage",
        choices=["planner", "decider", "predictor", "all"],
        required=True,
        help="planner: MaskablePPO on GCCPPlanner-v0; decider: MaskablePPO on GCCPDecider-v0 with the "
        "frozen --planner and GCCP on the side; predictor: the GCCP trajectory predictor alone; "
        "all: planner then decider",
    )
    parser.add_argument("--config", help="zoo-style YAML (default: zoo_configs/ppo_mask.yml)")
    parser.add_argument("--seed", type=seed_value, default=0)
    parser.add_argument("-n", "--n-timesteps", type=int, help="override the file's n_timesteps")
    parser.add_argument("--log-folder", default="runs", help="runs go to LOG_FOLDER/STAGE/ENV_SEED_TIME")
    parser.add_argument(
        "--resume",
        nargs="?",
        const="",
        metavar="RUN_DIR",
        help="continue a run from its last checkpoint (default: the newest run)",
    )
    # The run options default to None, "not given": a resume keeps the run's own (args.yml).
    parser.add_argument(
        "--save-freq",
        type=int,
        help="planner stage: env steps between checkpoints (default 10000; a resume keeps the run's)",
    )
    add_torch_threads(parser, "the learner")
    parser.set_defaults(torch_threads=None)
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        help="a progress bar (default: on; a resume keeps the run's)",
    )
    parser.add_argument("-v", "--verbose", type=int, help="SB3 verbosity: 0 (default), 1, 2")
    parser.add_argument(
        "--planner",
        help="frozen motion-planner .zip (decider and predictor stages), or 'scripted' (the scripted "
        "pure-pursuit planner)",
    )
    predictor = parser.add_argument_group("predictor stage")
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
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="world config key (repeatable) of every env the stage trains on, over the zoo entry's "
        "env_kwargs: --set traffic=sumo",
    )
    parser.add_argument(
        "--gccp",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="key (repeatable) of the decider entry's gccp map, decider and all stages: "
        "--gccp predictor=none trains w/o GCCP",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Train the stage asked for and print where its run went."""
    from sb3_gccp.hyperparams import HyperparamsError, default_config_file
    from sb3_gccp.training.decider import train_all, train_decider
    from sb3_gccp.training.planner import train_planner
    from sb3_gccp.training.run_folder import StageRequest, latest_run

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
    if args.set and resume is not None:
        raise CLIError("--set cannot change a resumed run's world: it keeps its config.yml")
    if args.gccp and resume is not None:
        raise CLIError("--gccp cannot change a resumed run's settings: it keeps its config.yml")
    if args.gccp and args.stage == "planner":
        raise CLIError("--gccp sets the decider's gccp map: use it with --stage decider or --stage all")
    world = parse_assignments(args.set)
    load_world_config(None, args.set)  # every key known and in range, before anything is written
    request = StageRequest(
        config_file=config_file,
        seed=args.seed,
        n_timesteps=args.n_timesteps,
        log_folder=Path(args.log_folder),
        resume=resume,
        progress_bar=args.progress,
        verbose=args.verbose,
        save_freq=args.save_freq,
        torch_threads=args.torch_threads,
        planner=Path(args.planner) if args.planner else None,
        world=world,
        gccp=parse_assignments(args.gccp, "--gccp"),
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    try:
        if args.stage == "planner":
            print(f"saved {train_planner(request)}")
        elif args.stage == "decider":
            run_dir = train_decider(request)
            print(f"saved {run_dir}")
            print(sample_efficiency(run_dir))
        else:
            planner, run_dir = train_all(request)
            print(f"saved {planner}")
            print(f"saved {run_dir}")
            print(sample_efficiency(run_dir))
            print(f"evaluate it: sb3_gccp evaluate --model {run_dir} --episodes-per-task 50 --seed 0")
    except (HyperparamsError, ValueError, OSError) as err:
        raise CLIError(str(err)) from err


def sample_efficiency(run_dir: Path) -> str:
    """One line from a decider run's ``metrics.json``: where the rolling success first passed 70 and
    90 % (the paper's Fig. 5 reading), and the rates at the end."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    firsts = {level: metrics[f"first_episode_success_{level}"] for level in (70, 90)}
    passed = ", ".join(f"{level} % {f'at episode {n}' if n else 'never'}" for level, n in firsts.items())
    return (
        f"rolling success over {metrics['window']} episodes first passed {passed}; at the end "
        f"{100 * metrics['final_success_rate']:.1f} % success, {100 * metrics['final_collision_rate']:.1f} % "
        "collisions"
    )


def _train_predictor(args: argparse.Namespace) -> None:
    from sb3_gccp.training.predictor import PredictorRequest, train_predictor_stage
    from sb3_gccp.training.run_folder import RunOptions

    world = dataclasses.asdict(load_world_config(None, args.set))
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
        progress_bar=args.progress is not False,
        torch_threads=RunOptions.torch_threads if args.torch_threads is None else args.torch_threads,
        world=world,
        predictor_kwargs=parse_assignments(args.predictor_set, "--predictor-set"),
        argv=["sb3_gccp", *sys.argv[1:]],
    )
    try:
        run_dir = train_predictor_stage(request)
    except (ValueError, OSError) as err:
        raise CLIError(str(err)) from err
    print(f"saved {run_dir}")
