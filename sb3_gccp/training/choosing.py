"""The decider run's model chosen on validation flows, as SB3's ``EvalCallback`` keeps its best model.

During training the GCCP callback saves candidates, each the decider with the predictor of its moment::

    candidates/<episodes>/      decider.zip, predictor.pt (when the predictor is learned)

After training every candidate and the final model play the validation flows (``gccp.choose_on_flows``,
traffic seeds kept apart from the test flows 0-49 and the held-out flows 1000-1199 of the docs), and the
run's ``decider.zip`` and ``predictor.pt`` become those of the one with the highest success there (then
fewer collisions, then the later). The final model stays as ``final/``; ``choice.json`` holds every
candidate's table. Evidence: docs/experiments/2026-12-02-choosing-the-checkpoint-on-validation-flows.md.
"""

from __future__ import annotations

import json
import shutil
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from torch import nn

from gccp_envs.config import TASKS
from sb3_gccp.constants import CHOICE_FILE, DECIDER_FILE, PREDICTOR_FILE
from sb3_gccp.evaluation import EpisodeResult, evaluate, summarize
from sb3_gccp.progress import new_bar
from sb3_gccp.training.checkpoints import write_atomically
from sb3_gccp.training.workers import worker_context

CANDIDATES_DIR = "candidates"
"""The candidates' folder in a decider run folder."""
FINAL_DIR = "final"
"""Where the final model goes when another candidate is chosen."""


def save_candidate(run_dir: Path, episodes: int, model: BaseAlgorithm, predictor: nn.Module | None) -> Path:
    """Write ``model`` and ``predictor`` into ``candidates/<episodes>/`` of ``run_dir``, whole or not."""
    from sb3_gccp.gccp.predictor import TrajectoryPredictor, save_predictor

    folder = run_dir / CANDIDATES_DIR / str(episodes)
    staging = folder.with_name(f".{episodes}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    model.save(staging / DECIDER_FILE)
    if isinstance(predictor, TrajectoryPredictor):
        save_predictor(predictor, staging / PREDICTOR_FILE)
    shutil.rmtree(folder, ignore_errors=True)  # a resume plays the episodes after its checkpoint again
    staging.rename(folder)
    return folder


def candidates(run_dir: Path) -> dict[str, Path]:
    """The run's candidates by name (their episode count), in the order they were saved."""
    folder = run_dir / CANDIDATES_DIR
    found = sorted((p for p in folder.glob("[0-9]*") if p.is_dir()), key=lambda p: int(p.name))
    return {p.name: p for p in found}


def choose_model(
    run_dir: Path, flows: int, episodes_per_task: int, workers: int = 1, progress: bool = False
) -> dict[str, Any] | None:
    """Evaluate the candidates and the run's final model on the validation flows, make the best the run's
    model, write ``choice.json`` and return what it holds (None when there is no candidate to compare).

    :param run_dir: a finished decider run folder (its ``hierarchy.yml`` names the final model)
    :param flows: the first traffic seed of the validation flows
    :param episodes_per_task: validation flows per task
    :param workers: processes evaluating side by side, one task of one candidate at a time (the tables do
        not depend on it)
    :param progress: a bar over the validation episodes, advanced as each task of a candidate is done
    """
    found = candidates(run_dir)
    if not found:
        return None
    names = [*found, FINAL_DIR]
    jobs = [
        (str(run_dir), _files(run_dir, found.get(name)), task, flows, episodes_per_task)
        for name in names
        for task in TASKS
    ]
    with new_bar(total=len(jobs) * episodes_per_task, enabled=progress, desc="validation", unit="ep") as bar:
        if workers > 1:
            with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=worker_context()) as pool:
                futures = [pool.submit(_validation_episodes, *job) for job in jobs]
                for future in as_completed(futures):
                    future.result()  # a failed job stops the choice here
                    bar.update(episodes_per_task)
                episodes = [future.result() for future in futures]
        else:
            episodes = []
            for job in jobs:
                episodes.append(_validation_episodes(*job))
                bar.update(episodes_per_task)
    by_name: dict[str, list[EpisodeResult]] = {name: [] for name in names}
    for name, results in zip((name for name in names for _ in TASKS), episodes, strict=True):
        by_name[name].extend(results)  # in task order, as one ``evaluate`` call plays them
    tables = [summarize(by_name[name]) for name in names]
    ranked = [(t["overall"]["success"], -t["overall"]["crashed"], i) for i, t in enumerate(tables)]
    chosen = names[max(ranked)[2]]
    if chosen != FINAL_DIR:
        _keep_final(run_dir)
        for name in (DECIDER_FILE, PREDICTOR_FILE):
            if (found[chosen] / name).is_file():
                write_atomically(run_dir / name, partial(shutil.copyfile, found[chosen] / name))
    choice = {
        "flows": flows,
        "episodes_per_task": episodes_per_task,
        "chosen": chosen,
        "tables": dict(zip(names, tables, strict=True)),
    }
    text = json.dumps(choice, indent=2) + "\n"
    write_atomically(run_dir / CHOICE_FILE, lambda path: path.write_text(text))
    return choice


def _files(run_dir: Path, candidate: Path | None) -> tuple[str, str | None]:
    """The decider and predictor files of a candidate (None: the final model), relative to ``run_dir``."""
    if candidate is None:
        return DECIDER_FILE, PREDICTOR_FILE
    relative = candidate.relative_to(run_dir)
    return str(relative / DECIDER_FILE), str(relative / PREDICTOR_FILE)


def _keep_final(run_dir: Path) -> None:
    final = run_dir / FINAL_DIR
    final.mkdir(exist_ok=True)
    for name in (DECIDER_FILE, PREDICTOR_FILE):
        if (run_dir / name).is_file() and not (final / name).is_file():
            write_atomically(final / name, partial(shutil.copyfile, run_dir / name))


def _validation_episodes(
    run_dir: str, files: tuple[str, str | None], task: str, flows: int, episodes_per_task: int
) -> list[EpisodeResult]:
    """One candidate's episodes of one task on the validation flows, as ``sb3_gccp evaluate`` plays them."""
    import torch as th

    from sb3_gccp.hierarchy import load_hierarchy

    th.set_num_threads(1)
    hierarchy = load_hierarchy(run_dir)
    decider, predictor = files
    weights = predictor if hierarchy.predictor_weights_file is not None else None
    hierarchy = replace(hierarchy, decider_file=decider, predictor_weights_file=weights)
    env = hierarchy.make_env({})
    try:
        policy = hierarchy.decider_policy(env.config, True, False)
        return evaluate(env, policy, [task], episodes_per_task, flows, progress=False)
    finally:
        env.close()
