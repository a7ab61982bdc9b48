"""Training and evaluating one run of a reproduction once: finished runs are reused.

Each record (``training.json``, ``evaluation.json``, ``predictor_errors.json``) is written atomically
once its work is done, so a run folder holding it is finished whatever killed the process after.
"""

from __future__ import annotations

import filecmp
import json
import math
import shutil
import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.monitor import load_results

from gccp_envs.config import DT, TASKS, IntersectionConfig
from sb3_gccp.constants import (
    BASELINE_FILE,
    CONFIG_FILE,
    EPISODES_FILE,
    EVALUATION_FILE,
    PLANNER_FILE,
    PREDICTOR_FILE,
    SCRIPTED,
    TRAINING_FILE,
)
from sb3_gccp.evaluation import evaluate, summarize
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor, load_predictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer, collect_decisions
from sb3_gccp.gccp.training import displacement_errors
from sb3_gccp.hierarchy import load_hierarchy
from sb3_gccp.reproduce.methods import Method
from sb3_gccp.reproduce.plan import Plan
from sb3_gccp.safe_loading import SavedModel
from sb3_gccp.training.baselines import has_checkpoint, load_baseline, train_baseline, write_baseline_spec
from sb3_gccp.training.checkpoints import write_atomically
from sb3_gccp.training.decider import train_decider
from sb3_gccp.training.episodes import read_episodes
from sb3_gccp.training.planner import train_planner
from sb3_gccp.training.predictor import HELDOUT_SEED_OFFSET
from sb3_gccp.training.run_folder import StageRequest

PREDICTOR_ERRORS_FILE = "predictor_errors.json"
"""In a seed's folder: Fig. 7's numbers for that seed."""


def finished_training(run_dir: Path) -> dict[str, Any] | None:
    """The training record of a run whose training finished, else None."""
    file = run_dir / TRAINING_FILE
    return json.loads(file.read_text()) if file.is_file() else None


def _saved(file: Path, key: Mapping[str, Any]) -> dict[str, Any] | None:
    """A JSON record if it exists and was made with the values of ``key``."""
    if not file.is_file():
        return None
    saved = json.loads(file.read_text())
    return saved if all(saved.get(k) == v for k, v in key.items()) else None


def _write_record(file: Path, record: Mapping[str, Any], indent: int = 2) -> None:
    write_atomically(file, lambda path: path.write_text(json.dumps(record, indent=indent) + "\n"))


def train_planner_once(plan: Plan, seed: int, label: str) -> tuple[Path, dict[str, Any]]:
    """The seed's motion-planner: trained (or continued), or the finished one; its path and record."""
    run_dir = plan.run_dir(seed, "planner")
    record = finished_training(run_dir)
    if record is not None:
        print(f"{label}: finished before, skipped", flush=True)
        return run_dir / PLANNER_FILE, record
    print(f"{label}: training for {plan.preset.planner_timesteps:,} steps", flush=True)
    start = time.perf_counter()
    path = train_planner(_stage_request(plan, plan.configs["planner"], seed, run_dir, None))
    record = {
        **planner_budget(path, run_dir / "monitor"),
        "wall_clock_s": round(time.perf_counter() - start, 1),
    }
    _write_record(run_dir / TRAINING_FILE, record)
    print(f"{label}: trained {record['timesteps']:,} steps in {record['wall_clock_s']:.0f} s", flush=True)
    return path, record


def planner_budget(path: Path, monitor: Path | None) -> dict[str, Any]:
    """Steps a planner was trained for and, when its Monitor files are at hand, its episodes."""
    episodes = None
    if monitor is not None and monitor.is_dir():
        episodes = len(load_results(str(monitor)))
    if path == Path(SCRIPTED):
        return {"planner": SCRIPTED, "timesteps": 0, "episodes": 0}
    timesteps = SavedModel.read(path).num_timesteps
    return {"planner": str(path), "timesteps": timesteps, "episodes": episodes}


def _stage_request(plan: Plan, config: Path, seed: int, run_dir: Path, planner: Path | None) -> StageRequest:
    """A training stage's request for a run in ``run_dir``: resumed if it started, else new there."""
    started = (run_dir / CONFIG_FILE).is_file()
    if run_dir.exists() and not started:  # made, but nothing written yet
        shutil.rmtree(run_dir)
    return StageRequest(
        config_file=config,
        seed=seed,
        resume=run_dir if started else None,
        run_dir=None if started else run_dir,
        progress_bar=plan.request.progress_bar,
        torch_threads=plan.request.torch_threads,
        planner=planner,
        argv=plan.request.argv,
    )


def train_method_once(
    plan: Plan, method: Method, seed: int, planner: Path | None, label: str
) -> dict[str, Any]:
    """Train a method for the preset's episodes unless its run finished before; return its record."""
    run_dir = plan.run_dir(seed, method.name)
    record = finished_method_training(plan, method, seed, planner)
    if record is not None:
        print(f"{label}: finished before, skipped", flush=True)
        return record
    print(f"{label}: training for {plan.preset.episodes:,} episodes", flush=True)
    start = time.perf_counter()
    if method.is_hierarchy:
        _train_hierarchy(plan, method, seed, planner, run_dir)
    else:
        _train_baseline(plan, method, seed, run_dir, label)
    history = read_episodes(run_dir / EPISODES_FILE)
    # The episode log's clock also counts the processes a resumed run ran in before this one.
    trained = history[-1]["wall_clock_s"] if history else None
    record = {
        "method": method.name,
        "seed": seed,
        "episodes": len(history),
        "timesteps": history[-1]["timesteps"] if history else 0,
        "wall_clock_s": round(time.perf_counter() - start if trained is None else trained, 1),
    }
    _write_record(run_dir / TRAINING_FILE, record)
    print(f"{label}: trained {record['episodes']} episodes in {record['wall_clock_s']:.0f} s", flush=True)
    return record


def finished_method_training(
    plan: Plan, method: Method, seed: int, planner: Path | None
) -> dict[str, Any] | None:
    """The training record of a method's finished run, else None.

    :raises ValueError: a finished hierarchy variant was trained over another planner than ``planner``
    """
    run_dir = plan.run_dir(seed, method.name)
    record = finished_training(run_dir)
    if (
        record is not None
        and method.is_hierarchy
        and planner is not None
        and not _same_planner(run_dir, planner)
    ):
        raise ValueError(
            f"{run_dir} was trained over another planner than {planner}: "
            "give the same --planner or another --log-folder"
        )
    return record


def _same_planner(run_dir: Path, planner: Path) -> bool:
    """Whether a finished hierarchy run was trained over ``planner`` (a ``.zip`` or 'scripted')."""
    trained = run_dir / PLANNER_FILE
    if planner == Path(SCRIPTED):
        return not trained.is_file()
    return trained.is_file() and filecmp.cmp(trained, planner, False)


def _train_hierarchy(plan: Plan, method: Method, seed: int, planner: Path | None, run_dir: Path) -> None:
    train_decider(_stage_request(plan, plan.configs[method.name], seed, run_dir, planner))


def _train_baseline(plan: Plan, method: Method, seed: int, run_dir: Path, label: str) -> None:
    resume = has_checkpoint(run_dir)
    if resume:
        print(f"{label}: continuing from the last checkpoint", flush=True)
    elif run_dir.exists():
        print(f"{label}: an unfinished run without a checkpoint starts over", flush=True)
        shutil.rmtree(run_dir)
    if plan.request.torch_threads is not None:
        th.set_num_threads(plan.request.torch_threads)
    train_baseline(
        method.algorithm,
        plan.configs[method.name],
        run_dir,
        seed,
        plan.preset.episodes,
        progress_bar=plan.request.progress_bar,
        description=label,
        resume=resume,
    )


def evaluate_once(plan: Plan, method: Method, seed: int, label: str) -> dict[str, Any]:
    """The method's evaluation on the preset's flows per task: computed, or read if it was before."""
    run_dir = plan.run_dir(seed, method.name)
    saved = finished_evaluation(plan, method.name, seed)
    if saved is not None:
        return saved
    print(f"{label}: evaluating on {plan.preset.episodes_per_task} traffic flow(s) per task", flush=True)
    env, policy = _evaluation_env_and_policy(method, run_dir)
    results = evaluate(
        env, policy, TASKS, plan.preset.episodes_per_task, plan.request.eval_seed, plan.request.progress_bar
    )
    saved = {**_evaluation_key(plan), "table": summarize(results), "episodes": [asdict(r) for r in results]}
    _write_record(run_dir / EVALUATION_FILE, saved, indent=1)
    overall = saved["table"]["overall"]
    print(f"{label}: success {overall['success']:.1f} %, collision {overall['crashed']:.1f} %", flush=True)
    return saved


def _evaluation_key(plan: Plan) -> dict[str, int]:
    return {"eval_seed": plan.request.eval_seed, "episodes_per_task": plan.preset.episodes_per_task}


def finished_evaluation(plan: Plan, name: str, seed: int) -> dict[str, Any] | None:
    """A method's evaluation if it was made on the plan's flows, else None."""
    return _saved(plan.run_dir(seed, name) / EVALUATION_FILE, _evaluation_key(plan))


def _evaluation_env_and_policy(method: Method, run_dir: Path) -> tuple[Any, Any]:
    if method.is_hierarchy:
        hierarchy = load_hierarchy(run_dir)
        option_env = hierarchy.make_env()
        return option_env, hierarchy.decider_policy(option_env.config)
    if not (run_dir / BASELINE_FILE).is_file():  # trained before baseline runs named their algorithm
        write_baseline_spec(run_dir, method.algorithm, masked=False)
    env, policy, _ = load_baseline(run_dir)
    return env, policy


def predictor_errors_once(plan: Plan, seed: int) -> dict[str, Any]:
    """Fig. 7's numbers for a seed: ADE/FDE of ours's, the no-goal ablation's and the CV predictor on
    decisions ours drives on held-out traffic seeds; computed once."""
    predictors = _predictors(plan, seed)
    saved = finished_predictor_errors(plan, seed)
    if saved is not None:
        return saved
    hierarchy = load_hierarchy(plan.run_dir(seed, "ours"))
    world = IntersectionConfig.from_dict(dict(hierarchy.world))
    per_episode = math.ceil(world.duration / (world.decision_period * DT)) + 1
    buffer = EpisodeReplayBuffer(capacity=plan.preset.heldout_episodes * per_episode)
    rng = np.random.default_rng(plan.request.eval_seed + HELDOUT_SEED_OFFSET)
    env = hierarchy.make_env()
    decisions = collect_decisions(
        env, hierarchy.decider_policy(env.config), plan.preset.heldout_episodes, buffer, rng
    )
    models = {name: load_predictor(path) for name, path in predictors.items()}
    errors = {
        name: displacement_errors(model, buffer)
        for name, model in {**models, "cv": ConstantVelocityPredictor()}.items()
    }
    saved = {**_predictor_errors_key(plan, seed), "decisions": decisions, "errors": errors}
    _write_record(plan.root / f"seed{seed}" / PREDICTOR_ERRORS_FILE, saved)
    return saved


def _predictors(plan: Plan, seed: int) -> dict[str, Path]:
    """Fig. 7's trained predictors of a seed: ours's, and the no-goal ablation's when it is run."""
    predictors = {"learned": plan.run_dir(seed, "ours") / PREDICTOR_FILE}
    if any(m.name == "without_goal" for m in plan.methods):
        predictors["no_goal"] = plan.run_dir(seed, "without_goal") / PREDICTOR_FILE
    return predictors


def _predictor_errors_key(plan: Plan, seed: int) -> dict[str, Any]:
    return {
        "eval_seed": plan.request.eval_seed,
        "heldout_episodes": plan.preset.heldout_episodes,
        "predictors": sorted(_predictors(plan, seed)),
    }


def finished_predictor_errors(plan: Plan, seed: int) -> dict[str, Any] | None:
    """Fig. 7's numbers of a seed if they were computed for the plan, else None."""
    return _saved(plan.root / f"seed{seed}" / PREDICTOR_ERRORS_FILE, _predictor_errors_key(plan, seed))
