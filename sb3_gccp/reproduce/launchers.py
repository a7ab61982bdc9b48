"""Where the jobs of a reproduction run: here one after another, in processes of this machine, or
through submitit (a Slurm cluster, or submitit's local executor where there is none).

:func:`run_jobs` hands each job to a launcher once the jobs it needs have finished, at most ``slots``
at a time, skips the jobs whose runs finished before and prints a line per job as it finishes.
"""

from __future__ import annotations

import functools
import importlib.util
import multiprocessing
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Protocol

from sb3_gccp.reproduce.collect import collect
from sb3_gccp.reproduce.jobs import Job, finished_job, job_graph, job_summary, run_job
from sb3_gccp.reproduce.plan import Plan
from sb3_gccp.training.workers import worker_context

POLL_SECONDS = 1.0
"""How often the jobs in flight are asked whether they finished."""
SUBMITIT_DEFAULTS = {"timeout_min": 24 * 60}
"""submitit parameters unless ``--launcher-set`` gives them (its own default time limit is 5 min)."""
SUBMITIT_MISSING = "--launcher submitit needs submitit: pip install 'sb3_gccp[cluster]'"


class JobFailed(Exception):
    """A job that ended with an error: its key and a one-line reason (the full trace is in its log)."""


class Handle(Protocol):
    """A job in flight."""

    def done(self) -> bool:
        """Whether it ended (finished or failed)."""

    def result(self) -> dict[str, Any]:
        """What :func:`~sb3_gccp.reproduce.jobs.run_job` returned.

        :raises JobFailed: it failed
        """

    def cancel(self) -> None:
        """Stop it."""


class Launcher(Protocol):
    """Starts jobs somewhere."""

    slots: int | None
    """Jobs in flight at once (None: no limit)."""

    def submit(self, job: Job, label: str) -> Handle:
        """Start ``job`` (``label`` names it in its own output)."""

    def output(self, job: Job) -> Path | None:
        """Where a job's output goes (None: this process's output)."""


# --- here, one job after another ------------------------------------------------------------------
class _Ended:
    """A job that ran in this process."""

    def __init__(self, result: dict[str, Any]) -> None:
        self._result = result

    def done(self) -> bool:
        return True

    def result(self) -> dict[str, Any]:
        return self._result

    def cancel(self) -> None:
        pass


class InProcessLauncher:
    """Runs each job in this process when it is submitted: ``--jobs 1``; its errors propagate as they are.

    :param plan_data: :meth:`~sb3_gccp.reproduce.plan.Plan.to_dict`
    """

    slots: int | None = 1

    def __init__(self, plan_data: Mapping[str, Any]) -> None:
        self.plan_data = plan_data

    def submit(self, job: Job, label: str) -> Handle:
        return _Ended(run_job(self.plan_data, job.key, label))

    def output(self, job: Job) -> Path | None:
        return None


# --- processes of this machine --------------------------------------------------------------------
def _child(conn: Connection, plan_data: Mapping[str, Any], key: str, label: str, log: str) -> None:
    """A job's process: output to its log, ends with its parent, sends back its result or its error."""
    parent = os.getppid()
    sys.stdout.flush()
    sys.stderr.flush()
    with open(log, "a") as file:  # descriptors, not sys.stdout: C extensions write there too
        os.dup2(file.fileno(), 1)
        os.dup2(file.fileno(), 2)
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()
    try:
        conn.send(("ok", run_job(plan_data, key, label)))
    except BaseException as err:  # the parent reports it; the trace goes to the log
        traceback.print_exc()
        sys.stderr.flush()
        conn.send(("error", f"{type(err).__name__}: {err}".splitlines()[0]))


def _exit_with(parent: int) -> None:
    # A killed reproduce must not leave jobs writing into run folders that its next run resumes.
    while os.getppid() == parent:
        time.sleep(2.0)
    os._exit(1)


class _ProcessJob:
    def __init__(self, process: multiprocessing.process.BaseProcess, conn: Connection, log: Path) -> None:
        self.process, self.conn, self.log = process, conn, log

    def done(self) -> bool:
        return self.conn.poll() or not self.process.is_alive()

    def result(self) -> dict[str, Any]:
        message = self.conn.recv() if self.conn.poll() else None
        self.process.join()
        if message is None:
            raise JobFailed(f"its process ended with exit code {self.process.exitcode}; output in {self.log}")
        status, value = message
        if status != "ok":
            raise JobFailed(f"{value}; output in {self.log}")
        return value

    def cancel(self) -> None:
        self.process.terminate()
        self.process.join()


class ProcessLauncher:
    """Runs each job in a new process of this machine (``--jobs N``, N > 1), its output in a log file.

    Each job forks from a server process that imported the package once and ran no torch op
    (``forkserver``; ``spawn`` where there is none): it sets its own torch threads and loads its own
    models.

    :param plan_data: :meth:`~sb3_gccp.reproduce.plan.Plan.to_dict`
    :param slots: jobs at once
    :param logs: the folder of the jobs' logs (``<key>.log``, ``/`` as ``_``)
    """

    def __init__(self, plan_data: Mapping[str, Any], slots: int, logs: Path) -> None:
        self.plan_data, self.logs = plan_data, logs
        self.slots: int | None = slots
        self._context: Any = worker_context()
        if self._context.get_start_method() == "forkserver":
            self._context.set_forkserver_preload([run_job.__module__])

    def output(self, job: Job) -> Path | None:
        return self.logs / f"{job.key.replace('/', '_')}.log"

    def submit(self, job: Job, label: str) -> Handle:
        log = self.output(job)
        assert log is not None
        self.logs.mkdir(parents=True, exist_ok=True)
        receiver, sender = self._context.Pipe(duplex=False)
        # Not a daemon: a job's training starts env workers of its own (SubprocVecEnv), and daemonic
        # processes may not have children. It still ends with this process (``_exit_with``).
        process = self._context.Process(
            target=_child, args=(sender, self.plan_data, job.key, label, str(log))
        )
        process.start()
        sender.close()
        return _ProcessJob(process, receiver, log)


# --- submitit -------------------------------------------------------------------------------------
class _SubmititJob:
    def __init__(self, job: Any) -> None:
        self.job = job

    def done(self) -> bool:
        return bool(self.job.done())

    def result(self) -> dict[str, Any]:
        from submitit.core.utils import FailedJobError, UncompletedJobError

        try:
            return self.job.result()
        except (FailedJobError, UncompletedJobError) as err:
            lines = [line for line in str(err).splitlines() if line.strip()]
            reason = lines[-1].strip() if lines else type(err).__name__
            raise JobFailed(f"{reason}; output in {self.job.paths.stderr}") from err

    def cancel(self) -> None:
        self.job.cancel(check=False)


class SubmititLauncher:
    """Submits each job through submitit's ``AutoExecutor``: Slurm where ``sbatch`` is, else submitit's
    local executor (a process per job on this machine).

    :param plan_data: :meth:`~sb3_gccp.reproduce.plan.Plan.to_dict`
    :param folder: submitit's folder (its pickles and each job's stdout and stderr)
    :param slots: jobs in flight at once (None: every job that is ready)
    :param parameters: ``update_parameters`` keywords (``timeout_min``, ``slurm_partition``, ...) over
        :data:`SUBMITIT_DEFAULTS`
    :raises ValueError: submitit is not installed, or refuses a parameter
    """

    def __init__(
        self, plan_data: Mapping[str, Any], folder: Path, slots: int | None, parameters: Mapping[str, Any]
    ) -> None:
        try:
            import submitit
        except ImportError as err:
            raise ValueError(SUBMITIT_MISSING) from err
        self.plan_data, self.slots = plan_data, slots
        self.executor = submitit.AutoExecutor(folder=folder)
        try:
            self.executor.update_parameters(**{**SUBMITIT_DEFAULTS, **parameters})
        except (ValueError, TypeError, AssertionError) as err:
            raise ValueError(f"--launcher-set: {str(err).splitlines()[0]}") from err

    def output(self, job: Job) -> Path | None:
        return Path(self.executor.folder)

    def submit(self, job: Job, label: str) -> Handle:
        self.executor.update_parameters(name=f"sb3_gccp_{job.key.replace('/', '_')}")
        return _SubmititJob(self.executor.submit(run_job, self.plan_data, job.key, label))


# --- the scheduler --------------------------------------------------------------------------------
def run_jobs(
    jobs: Sequence[Job], launcher: Launcher, finished: Callable[[Job], dict[str, Any] | None]
) -> None:
    """Run every job once the jobs it needs finished, at most ``launcher.slots`` at a time.

    A job whose run finished before is skipped (and said so). After a failure no new job starts; the
    ones in flight finish, then the failures are raised together.

    :param finished: a finished job's result, or None (checked before a job starts)
    :raises JobFailed: one line naming every failed job and the jobs left waiting for them
    """
    number = {job.key: f"[{i}/{len(jobs)}] {job.label}" for i, job in enumerate(jobs, 1)}
    done: set[str] = set()
    waiting = []
    for job in jobs:
        if finished(job) is not None:
            print(f"{number[job.key]}: finished before, skipped", flush=True)
            done.add(job.key)
        else:
            waiting.append(job)
    running: dict[str, tuple[Job, Handle, float]] = {}
    failed: list[str] = []
    try:
        while waiting or running:
            ready = [j for j in waiting if set(j.needs) <= done] if not failed else []
            for job in ready:
                if launcher.slots is not None and len(running) >= launcher.slots:
                    break
                waiting.remove(job)
                output = launcher.output(job)
                if output is not None:
                    print(f"{number[job.key]}: started, output in {output}", flush=True)
                started = time.perf_counter()
                running[job.key] = (job, launcher.submit(job, number[job.key]), started)
            ended = [key for key, (_, handle, _) in running.items() if handle.done()]
            if not ended:
                if not running:
                    break  # the rest wait for failed jobs
                time.sleep(POLL_SECONDS)
                continue
            for key in ended:
                job, handle, started = running.pop(key)
                try:
                    summary = job_summary(handle.result())
                except JobFailed as err:
                    print(f"{number[key]}: failed: {err}", flush=True)
                    failed.append(f"{job.label}: {err}")
                    continue
                done.add(key)
                seconds = time.perf_counter() - started
                print(
                    f"{number[key]}: finished in {seconds:.0f} s, {summary} ({len(done)}/{len(jobs)} done)",
                    flush=True,
                )
    finally:
        for _, handle, _ in running.values():
            handle.cancel()
    if failed:
        left = f"; not started: {', '.join(j.label for j in waiting)}" if waiting else ""
        raise JobFailed(f"{len(failed)} job(s) failed: {'; '.join(failed)}{left}")


LAUNCHERS = ("local", "submitit")
"""``--launcher`` choices."""


def make_launcher(
    plan: Plan, name: str = "local", slots: int | None = None, parameters: Mapping[str, Any] | None = None
) -> Launcher:
    """The launcher of ``--launcher NAME --jobs SLOTS --launcher-set KEY=VALUE``.

    :param slots: jobs at once; None: 1 here, every ready job through submitit
    :raises ValueError: a bad choice, with a one-line reason
    """
    check_launcher(name, slots, parameters)
    if name == "submitit":
        return SubmititLauncher(plan.to_dict(), plan.root / "submitit", slots, parameters or {})
    if slots is None or slots == 1:
        return InProcessLauncher(plan.to_dict())
    return ProcessLauncher(plan.to_dict(), slots, plan.root / "logs")


def check_launcher(name: str, slots: int | None, parameters: Mapping[str, Any] | None) -> None:
    """Refuse launcher options that cannot work, before anything is written.

    :raises ValueError: with a one-line reason
    """
    if name not in LAUNCHERS:
        raise ValueError(f"unknown launcher {name!r}: expected {' or '.join(LAUNCHERS)}")
    if slots is not None and slots < 1:
        raise ValueError(f"--jobs must be at least 1, got {slots}")
    if parameters and name != "submitit":
        raise ValueError("--launcher-set is for --launcher submitit")
    if name == "submitit" and importlib.util.find_spec("submitit") is None:
        raise ValueError(SUBMITIT_MISSING)


def reproduce(plan: Plan, launcher: Launcher | None = None) -> dict[str, Any]:
    """Run every job of a plan that has not finished, then write the tables, data and figures.

    :param launcher: where the jobs run (default: here, one after another)
    :return: what ``results.json`` holds
    """
    started = time.perf_counter()
    run_jobs(job_graph(plan), launcher or make_launcher(plan), functools.partial(finished_job, plan))
    return collect(plan, started)
