"""The tables, data and figures of a reproduction, read from its finished run folders alone.

``reproduce`` ends here once its jobs are done; ``reproduce --collect OUT`` comes here directly, for
runs made by other processes or on other machines, and trains nothing.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gccp_envs.config import TASKS
from sb3_gccp.constants import EPISODES_FILE, EVALUATION_FILE, TRAINING_FILE
from sb3_gccp.reproduce.methods import METHODS, PAPER_RESULTS
from sb3_gccp.reproduce.plan import Plan, mask_after_episodes
from sb3_gccp.reproduce.report import aggregate, write_outputs
from sb3_gccp.reproduce.runner import (
    PREDICTOR_ERRORS_FILE,
    finished_evaluation,
    finished_predictor_errors,
    finished_training,
    planner_budget,
)

RECORDS_DIR = "records"
"""In ``<out>``: every run's records (:data:`RECORD_FILES`) and each seed's Fig. 7 numbers, laid out as the
reproduction's folder (``seed<k>/<method>/``), so that the outputs hold every episode behind the tables."""
RECORD_FILES = (TRAINING_FILE, EVALUATION_FILE, EPISODES_FILE)
"""A run's records: the training record, every evaluation episode, every training episode."""


class UnfinishedRuns(ValueError):
    """Runs the tables need that have not finished (a one-line message naming them)."""


def collect(plan: Plan, started: float | None = None) -> dict[str, Any]:
    """Write the tables, ``results.csv``, ``results.json`` and the figures into ``<out>`` from the plan's
    finished runs.

    :param started: ``time.perf_counter()`` when the command started (``results.json``'s wall clock)
    :return: what ``results.json`` holds
    :raises UnfinishedRuns: a run is missing or unfinished (its training, its evaluation on the plan's
        flows, or Fig. 7's numbers of a seed); nothing is written then
    """
    started = time.perf_counter() if started is None else started
    request = plan.request
    missing: list[str] = []
    planners: dict[int, dict[str, Any]] = {}
    runs: dict[str, dict[int, dict[str, Any]]] = {m.name: {} for m in plan.methods}
    errors: dict[int, dict[str, Any]] = {}
    for seed in request.seeds:
        if plan.trains_planner:
            record = finished_training(plan.run_dir(seed, "planner"))
            if record is None:
                missing.append(f"seed{seed}/planner")
            else:
                planners[seed] = record
        elif request.planner is not None:
            planners[seed] = {**planner_budget(request.planner, None), "given": True}
        for method in plan.methods:
            run_dir = plan.run_dir(seed, method.name)
            training = finished_training(run_dir)
            evaluation = finished_evaluation(plan, method.name, seed)
            if training is None or evaluation is None:
                missing.append(f"seed{seed}/{method.name}" + ("" if training is None else " (evaluation)"))
                continue
            runs[method.name][seed] = {
                "run_dir": str(run_dir),
                "training": training,
                "table": evaluation["table"],
            }
        if "ours" in runs:
            saved = finished_predictor_errors(plan, seed)
            if saved is None:
                missing.append(f"seed{seed}/{PREDICTOR_ERRORS_FILE}")
            else:
                errors[seed] = saved
    if missing:
        raise UnfinishedRuns(
            f"unfinished in {plan.root}: {', '.join(missing)}: run reproduce with the same options to "
            "finish them, or leave them out with --seeds/--methods"
        )
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
    request.out.mkdir(parents=True, exist_ok=True)
    plan.write_configs()
    copy_records(plan, request.out / RECORDS_DIR, errors)
    write_outputs(plan, runs, errors)
    results["wall_clock_s"] = round(time.perf_counter() - started, 1)
    (request.out / "results.json").write_text(strict_json(results) + "\n")
    return results


def strict_json(value: Any) -> str:
    """``value`` as JSON that any parser reads: a float that is not finite (a predictor error over no
    neighbour is NaN) is written as ``null``, not as Python's ``NaN``."""

    def finite(item: Any) -> Any:
        if isinstance(item, float) and not math.isfinite(item):
            return None
        if isinstance(item, Mapping):
            return {key: finite(entry) for key, entry in item.items()}
        if isinstance(item, list | tuple):
            return [finite(entry) for entry in item]
        return item

    return json.dumps(finite(value), indent=2, allow_nan=False)


def copy_records(plan: Plan, folder: Path, errors: Mapping[int, Any]) -> None:
    """Copy the records of the plan's runs, and the Fig. 7 numbers of the seeds in ``errors``, into
    ``folder``."""
    for seed in plan.request.seeds:
        for method in plan.methods:
            target = folder / f"seed{seed}" / method.name
            target.mkdir(parents=True, exist_ok=True)
            for name in RECORD_FILES:
                shutil.copyfile(plan.run_dir(seed, method.name) / name, target / name)
    for seed in errors:
        name = f"seed{seed}/{PREDICTOR_ERRORS_FILE}"
        shutil.copyfile(plan.root / name, folder / name)
