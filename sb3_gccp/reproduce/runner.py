"""Training and evaluating every method of a reproduction once: finished runs are reused."""

from __future__ import annotations

import filecmp
import json
import math
import shutil
import time
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
from sb3_gccp.reproduce.methods import METHODS, PAPER_RESULTS, Method
from sb3_gccp.reproduce.plan import Plan, mask_after_episodes
from sb3_gccp.reproduce.report import aggregate, write_outputs
from sb3_gccp.safe_loading import SavedModel
from sb3_gccp.training.baselines import has_checkpoint, load_baseline, train_baseline, write_baseline_spec
from sb3_gccp.training.decider import train_decider
from sb3_gccp.training.episodes import read_episodes
from sb3_gccp.training.planner import train_planner
from sb3_gccp.training.predictor import HELDOUT_SEED_OFFSET
from sb3_gccp.training.run_folder import StageRequest


def _finished(run_dir: Path) -> dict[str, Any] | None:
    file = run_dir / TRAINING_FILE
    return json.loads(file.read_text()) if file.is_file() else None


def train_planner_once(plan: Plan, seed: int, label: str) -> tuple[Path, dict[str, Any]]:
    """The seed's motion-planner: trained (or continued), or the finished one; its path and record."""
    run_dir = plan.root / f"seed{seed}" / "planner"
    record = _finished(run_dir)
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
    (run_dir / TRAINING_FILE).write_text(json.dumps(record, indent=2) + "\n")
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
    run_dir = plan.root / f"seed{seed}" / method.name
    record = _finished(run_dir)
    if record is not None:
        if method.is_hierarchy and planner is not None and not _same_planner(run_dir, planner):
            raise ValueError(
                f"{run_dir} was trained over another planner than {planner}: "
                "give the same --planner or another --log-folder"
            )
        print(f"{label}: finished before, skipped", flush=True)
        return record
    print(f"{label}: training for {plan.preset.episodes:,} episodes", flush=True)
    start = time.perf_counter()
    if method.is_hierarchy:
        _train_hierarchy(plan, method, seed, planner, run_dir)
    else:
        _train_baseline(plan, method, seed, run_dir, label)
    history = read_episodes(run_dir / EPISODES_FILE)
    record = {
        "method": method.name,
        "seed": seed,
        "episodes": len(history),
        "timesteps": history[-1]["timesteps"] if history else 0,
        "wall_clock_s": round(time.perf_counter() - start, 1),
    }
    (run_dir / TRAINING_FILE).write_text(json.dumps(record, indent=2) + "\n")
    print(f"{label}: trained {record['episodes']} episodes in {record['wall_clock_s']:.0f} s", flush=True)
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
    run_dir = plan.root / f"seed{seed}" / method.name
    key = {"eval_seed": plan.request.eval_seed, "episodes_per_task": plan.preset.episodes_per_task}
    file = run_dir / EVALUATION_FILE
    if file.is_file():
        saved = json.loads(file.read_text())
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    print(f"{label}: evaluating on {plan.preset.episodes_per_task} traffic flow(s) per task", flush=True)
    env, policy = _evaluation_env_and_policy(method, run_dir)
    results = evaluate(
        env, policy, TASKS, plan.preset.episodes_per_task, plan.request.eval_seed, plan.request.progress_bar
    )
    saved = {**key, "table": summarize(results), "episodes": [asdict(r) for r in results]}
    file.write_text(json.dumps(saved, indent=1) + "\n")
    overall = saved["table"]["overall"]
    print(f"{label}: success {overall['success']:.1f} %, collision {overall['crashed']:.1f} %", flush=True)
    return saved


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
    seed_dir = plan.root / f"seed{seed}"
    predictors = {"learned": seed_dir / "ours" / PREDICTOR_FILE}
    if any(m.name == "without_goal" for m in plan.methods):
        predictors["no_goal"] = seed_dir / "without_goal" / PREDICTOR_FILE
    key = {
        "eval_seed": plan.request.eval_seed,
        "heldout_episodes": plan.preset.heldout_episodes,
        "predictors": sorted(predictors),
    }
    file = seed_dir / "predictor_errors.json"
    if file.is_file():
        saved = json.loads(file.read_text())
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    hierarchy = load_hierarchy(seed_dir / "ours")
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
    saved = {**key, "decisions": decisions, "errors": errors}
    file.write_text(json.dumps(saved, indent=2) + "\n")
    return saved


# --- the whole reproduction ------------------------------------------------------------------------
def reproduce(plan: Plan) -> dict[str, Any]:
    """Train and evaluate every method for every seed, then write the tables, data and figures.

    :return: what ``results.json`` holds
    """
    started = time.perf_counter()
    request = plan.request
    total = len(request.seeds) * (len(plan.methods) + int(plan.trains_planner))
    step = 0
    runs: dict[str, dict[int, dict[str, Any]]] = {m.name: {} for m in plan.methods}
    planners: dict[int, dict[str, Any]] = {}
    for seed in request.seeds:
        planner = request.planner
        if plan.trains_planner:
            step += 1
            planner, planners[seed] = train_planner_once(plan, seed, f"[{step}/{total}] seed {seed} planner")
        elif planner is not None:
            planners[seed] = {**planner_budget(planner, None), "given": True}
        for method in plan.methods:
            step += 1
            label = f"[{step}/{total}] seed {seed} {method.name}"
            training = train_method_once(plan, method, seed, planner, label)
            evaluation = evaluate_once(plan, method, seed, label)
            runs[method.name][seed] = {
                "run_dir": str(plan.root / f"seed{seed}" / method.name),
                "training": training,
                "table": evaluation["table"],
            }
    errors = {}
    if "ours" in runs:
        errors = {seed: predictor_errors_once(plan, seed) for seed in request.seeds}
    results = {
        "preset": request.preset,
        "settings": plan.preset.to_dict(),
        "seeds": list(request.seeds),
        "eval_seed": request.eval_seed,
        "episodes_per_task": plan.preset.episodes_per_task,
        "budget": {
            "episodes_per_method": plan.preset.episodes,
            "mask_after_episodes": mask_after_episodes(plan.preset),
            "planner_pretraining": {str(s): p for s, p in planners.items()},
        },
        "methods": {
            name: {"label": METHODS[name].label, "runs": {str(s): r for s, r in seed_runs.items()}}
            for name, seed_runs in runs.items()
        },
        "tables": {
            name: aggregate([r["table"] for r in seed_runs.values()]) for name, seed_runs in runs.items()
        },
        "predictor_errors": {str(s): e for s, e in errors.items()},
        "paper": {
            name: dict(zip((*TASKS, "overall"), rows, strict=True)) for name, rows in PAPER_RESULTS.items()
        },
    }
    write_outputs(plan, runs, errors)
    results["wall_clock_s"] = round(time.perf_counter() - started, 1)
    (request.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results
