"""A reproduction as independent jobs: one per (method, seed) run, each in its own run folder.

The hierarchy variants of a seed wait for that seed's planner job (none with ``--planner``); the
baselines wait for nothing; Fig. 7's numbers of a seed wait for ours (and the no-goal ablation).
:func:`run_job` is what a launcher runs: a module-level function of plain data, so that it pickles
for another process or a cluster node.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch as th

from sb3_gccp.constants import PLANNER_FILE
from sb3_gccp.reproduce.methods import METHODS
from sb3_gccp.reproduce.plan import Plan
from sb3_gccp.reproduce.runner import (
    PREDICTOR_ERRORS_FILE,
    evaluate_once,
    finished_evaluation,
    finished_method_training,
    finished_predictor_errors,
    finished_training,
    predictor_errors_once,
    train_method_once,
    train_planner_once,
)

PLANNER_JOB = "planner"
"""The job (and run folder) name of a seed's motion-planner."""
PREDICTOR_ERRORS_JOB = "predictor_errors"
"""The job name of a seed's Fig. 7 numbers (written to ``seed<k>/predictor_errors.json``)."""


@dataclass(frozen=True)
class Job:
    """One job of a reproduction."""

    seed: int
    """The training seed."""
    name: str
    """A method's name, :data:`PLANNER_JOB` or :data:`PREDICTOR_ERRORS_JOB`."""
    needs: tuple[str, ...] = ()
    """Keys of the jobs that must finish first."""

    @property
    def key(self) -> str:
        """``seed<k>/<name>``: unique in a reproduction, and the run folder below its root."""
        return f"seed{self.seed}/{self.name}"

    @property
    def label(self) -> str:
        """How progress lines name it."""
        return f"seed {self.seed} {self.name}"


def job_graph(plan: Plan) -> list[Job]:
    """Every job of a plan, each after the jobs it needs: per seed the planner (unless one is given),
    the methods in the tables' order, then Fig. 7's numbers."""
    names = [m.name for m in plan.methods]
    jobs = []
    for seed in plan.request.seeds:
        planner: tuple[str, ...] = ()
        if plan.trains_planner:
            jobs.append(Job(seed, PLANNER_JOB))
            planner = (jobs[-1].key,)
        jobs.extend(Job(seed, m.name, planner if m.is_hierarchy else ()) for m in plan.methods)
        if "ours" in names:
            needs = tuple(f"seed{seed}/{n}" for n in ("ours", "without_goal") if n in names)
            jobs.append(Job(seed, PREDICTOR_ERRORS_JOB, needs))
    return jobs


def seed_planner(plan: Plan, seed: int) -> Path | None:
    """The motion-planner of a seed's hierarchy variants: the given one, or the seed's planner run's."""
    if plan.trains_planner:
        return plan.run_dir(seed, PLANNER_JOB) / PLANNER_FILE
    return plan.request.planner


def finished_job(plan: Plan, job: Job) -> dict[str, Any] | None:
    """What a finished job left in its run folder (as :func:`run_job` returns it), else None.

    :raises ValueError: a finished hierarchy variant was trained over another planner
    """
    if job.name == PLANNER_JOB:
        return finished_training(plan.run_dir(job.seed, PLANNER_JOB))
    if job.name == PREDICTOR_ERRORS_JOB:
        saved = finished_predictor_errors(plan, job.seed)
        return None if saved is None else {"decisions": saved["decisions"]}
    training = finished_method_training(plan, METHODS[job.name], job.seed, seed_planner(plan, job.seed))
    evaluation = finished_evaluation(plan, job.name, job.seed)
    if training is None or evaluation is None:
        return None
    return {**training, "overall": evaluation["table"]["overall"]}


def run_job(plan_data: Mapping[str, Any], key: str, label: str) -> dict[str, Any]:
    """Run one job of a plan: train its run (or continue it), evaluate it; skip what finished before.

    :param plan_data: :meth:`Plan.to_dict`
    :param key: the job's :attr:`Job.key`
    :param label: how its own progress lines name it
    :return: the training record (for a method, with its overall evaluation under 'overall')
    """
    plan = Plan.from_dict(plan_data)
    job = next(j for j in job_graph(plan) if j.key == key)
    if plan.request.torch_threads is not None:  # this process's, set by its entry point
        th.set_num_threads(plan.request.torch_threads)
    if job.name == PLANNER_JOB:
        return train_planner_once(plan, job.seed, label)[1]
    if job.name == PREDICTOR_ERRORS_JOB:
        return {"decisions": predictor_errors_once(plan, job.seed)["decisions"]}
    method = METHODS[job.name]
    planner = seed_planner(plan, job.seed) if method.is_hierarchy else None
    training = train_method_once(plan, method, job.seed, planner, label)
    evaluation = evaluate_once(plan, method, job.seed, label)
    return {**training, "overall": evaluation["table"]["overall"]}


def job_summary(result: Mapping[str, Any]) -> str:
    """A job's result in a few words, for its progress line."""
    if "overall" in result:
        overall = result["overall"]
        return f"success {overall['success']:.1f} %, collision {overall['crashed']:.1f} %"
    if "decisions" in result:
        return f"{PREDICTOR_ERRORS_FILE} from {result['decisions']} decisions"
    return f"{result['timesteps']:,} steps"
