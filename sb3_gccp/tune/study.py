"""An Optuna study of ``sb3_gccp tune``: its storage, its worker processes, resuming it, and its best
trial as a zoo entry.

Output folder::

    <out>/study.db                  the default storage (SQLite; every study of the folder)
    <out>/<study>/trial_<number>/   one run folder per trial (a baseline's or a decider's)
    <out>/<study>/best.yml          the best trial's hyperparameters as a zoo entry, keyed by env id

A study is shared by every process started with the same ``--study-name`` and ``--storage``, on one
machine (``--n-jobs``) or many: each runs trials until the study holds ``--n-trials`` finished (complete
or pruned) ones. A trial left running by a process that died is failed and run again with the same
hyperparameters: at once when the process ran on this machine (its host name and process id are on the
trial), after the heartbeat's grace period otherwise (RDB storages only).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import socket
import textwrap
import time
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import optuna
import torch as th
import yaml
from optuna.trial import FrozenTrial, TrialState

from sb3_gccp.progress import new_bar
from sb3_gccp.tune.objective import WINDOW, TrialSettings, run_trial, with_values

JOURNAL_SCHEME = "journal://"
"""``--storage journal://PATH``: Optuna's JournalStorage on the file PATH (a shared disk for many
machines); any other URL is an SQLAlchemy URL for Optuna's RDBStorage."""
STORAGE_FILE = "study.db"
"""The default storage, an SQLite file in the output folder."""
BEST_FILE = "best.yml"
"""The best trial's zoo entry, in the study's folder."""
HEARTBEAT_INTERVAL = 60
"""Seconds between the heartbeats of a running trial (RDB storages)."""
GRACE_PERIOD = 300
"""Seconds without a heartbeat after which a running trial counts as dead (RDB storages)."""
MAX_RETRY = 3
"""Times a trial whose process died is run again."""
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
"""The trials that count towards ``--n-trials``."""
POLL_SECONDS = 2.0
"""Seconds between two looks at the study while worker processes run."""


@dataclass(frozen=True)
class Study:
    """A study of ``sb3_gccp tune``: plain data, so that worker processes receive it."""

    name: str
    storage_url: str
    n_trials: int
    """Finished trials the study should hold."""
    trials: TrialSettings
    n_jobs: int = 1
    """Worker processes on this machine."""
    progress_bar: bool = True

    @property
    def attributes(self) -> dict[str, Any]:
        """What every process joining the study must agree on (kept as the study's user attributes)."""
        return json.loads(
            json.dumps(
                {
                    "method": self.trials.method.name,
                    "episodes_per_trial": self.trials.episodes,
                    "space": self.trials.space.to_dict(),
                    "entry": self.trials.entry,
                }
            )
        )


def open_storage(url: str) -> optuna.storages.BaseStorage:
    """The storage of ``--storage``: a journal file, or an RDB (with heartbeats) for any other URL.

    :raises ValueError: an URL that SQLAlchemy or Optuna cannot open, in one line
    """
    retry = _retry_callback()
    if url.startswith(JOURNAL_SCHEME):
        path = Path(url[len(JOURNAL_SCHEME) :])
        if not path.name or not path.parent.is_dir():
            raise ValueError(f"--storage {url}: no folder {path.parent} for the journal file")
        from optuna.storages.journal import JournalFileBackend

        return optuna.storages.JournalStorage(JournalFileBackend(str(path)))
    try:
        with warnings.catch_warnings():  # heartbeats are "experimental" since Optuna 2.9
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(
                url,
                heartbeat_interval=HEARTBEAT_INTERVAL,
                grace_period=GRACE_PERIOD,
                heartbeat_stale_trial_callback=retry,
            )
    except Exception as err:  # SQLAlchemy's errors have no common base short of Exception
        raise ValueError(f"--storage {display_url(url)}: {str(err).splitlines()[0]}") from err


def display_url(url: str) -> str:
    """A storage URL without its password, for messages and files."""
    if url.startswith(JOURNAL_SCHEME):
        return url
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # not an URL at all: nothing to hide
        return url


def _retry_callback() -> Callable[[optuna.Study, FrozenTrial], None]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)


def open_study(study: Study) -> optuna.Study:
    """Create the study, or join it; a study made for another method, budget, space or entry is refused.

    :raises ValueError: one line saying what differs
    """
    pruner = study.trials.space.pruner.make(study.trials.episodes)
    optuna_study = optuna.create_study(
        storage=open_storage(study.storage_url),
        study_name=study.name,
        direction="maximize",
        pruner=pruner,
        load_if_exists=True,
    )
    recorded = optuna_study.user_attrs
    differ = [key for key, value in study.attributes.items() if key in recorded and recorded[key] != value]
    if differ:
        raise ValueError(
            f"study {study.name!r} in {display_url(study.storage_url)} was made with another "
            f"{', '.join(differ)}: give the same ones or another --study-name"
        )
    for key, value in study.attributes.items():
        if key not in recorded:
            optuna_study.set_user_attr(key, value)
    return optuna_study


def count(study: optuna.Study, states: tuple[TrialState, ...]) -> int:
    """Trials of the study in one of ``states``."""
    return len(study.get_trials(deepcopy=False, states=states))


def _process_start(pid: int) -> str:
    """When process ``pid`` started (Linux: its start time in clock ticks), to tell a reused process id
    apart; empty where it cannot be read."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def _this_process() -> dict[str, Any]:
    pid = os.getpid()
    return {"host": socket.gethostname(), "pid": pid, "pid_start": _process_start(pid)}


def _is_dead(worker: dict[str, Any]) -> bool:
    """Whether the process that ran a trial (its ``_this_process`` record) is known to have ended."""
    if worker.get("host") != socket.gethostname() or not isinstance(worker.get("pid"), int):
        return False  # another machine's: left to the heartbeat
    try:
        os.kill(worker["pid"], 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return _process_start(worker["pid"]) != worker.get("pid_start", "")


def retry_dead_trials(study: optuna.Study) -> list[int]:
    """Fail the running trials whose process on this machine has ended, and queue each again with the
    same hyperparameters; return the numbers of the failed trials."""
    failed = []
    retry = _retry_callback()
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        if not _is_dead(trial.user_attrs.get("worker") or {}):
            continue
        try:
            frozen = study.tell(trial.number, state=TrialState.FAIL)
        except (ValueError, RuntimeError):  # another process failed it first
            continue
        retry(study, frozen)
        failed.append(trial.number)
    return failed


def retry_interrupted_trials(study: optuna.Study) -> None:
    """Queue again, with the same hyperparameters, the trials of this process that Optuna failed when
    it was interrupted (Ctrl-C)."""
    retry, me = _retry_callback(), _this_process()
    retried = {t.system_attrs.get("failed_trial") for t in study.get_trials(deepcopy=False)}
    for trial in study.get_trials(deepcopy=False, states=(TrialState.FAIL,)):
        if trial.user_attrs.get("worker") == me and trial.number not in retried:
            retry(study, trial)


def objective(study: Study) -> Callable[[optuna.Trial], float]:
    """The objective of a worker: names the process on the trial, then trains it."""

    def run(trial: optuna.Trial) -> float:
        trial.set_user_attr("worker", _this_process())
        return run_trial(trial, study.trials)

    return run


def run_worker(study: Study, index: int, on_trial: Callable[[optuna.Study], None] | None = None) -> None:
    """Run trials until the study holds ``n_trials`` finished ones (counting those running elsewhere).

    :param index: the worker's number on this machine
    :param on_trial: called after every trial (the progress bar of a single worker)
    """
    th.set_num_threads(study.trials.torch_threads)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # A sampler seeded alike in two processes, or in two calls of one, proposes the same random first
    # trials: each draws from its own seed (the process, and the trials the study already holds).
    optuna_study = open_study(study)
    key = f"{study.trials.seed}:{index}:{_this_process()}:{len(optuna_study.trials)}"
    optuna_study.sampler = optuna.samplers.TPESampler(seed=zlib.crc32(key.encode()))
    run = objective(study)
    while True:
        retry_dead_trials(optuna_study)
        if count(optuna_study, (*FINISHED, TrialState.RUNNING)) >= study.n_trials:
            return
        try:
            optuna_study.optimize(run, n_trials=1)
        except KeyboardInterrupt:
            retry_interrupted_trials(optuna_study)
            raise
        if on_trial is not None:
            on_trial(optuna_study)


def _worker_main(study: Study, index: int) -> None:
    run_worker(study, index)


def run_study(study: Study) -> optuna.Study:
    """Run the study's trials in ``n_jobs`` processes (one: in this process), a progress bar over
    trials; return the study.

    :raises RuntimeError: a worker process failed
    """
    optuna_study = open_study(study)
    retry_dead_trials(optuna_study)
    bar = new_bar(total=study.n_trials, desc=study.name, unit="trial", enabled=study.progress_bar)

    def show(current: optuna.Study) -> None:
        bar.n = min(count(current, FINISHED), study.n_trials)
        done = current.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if done:
            bar.set_postfix(best=f"{max(t.value for t in done if t.value is not None):.2f}", refresh=False)
        bar.refresh()

    show(optuna_study)
    try:
        if study.n_jobs == 1:
            run_worker(study, 0, show)
        else:
            _run_processes(study, lambda: show(optuna_study))
        show(optuna_study)  # trials that other processes finished meanwhile
    finally:
        bar.close()
    return optuna_study


def _run_processes(study: Study, show: Callable[[], None]) -> None:
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_worker_main, args=(study, i)) for i in range(study.n_jobs)]
    for worker in workers:
        worker.start()
    try:
        while any(worker.is_alive() for worker in workers):
            time.sleep(POLL_SECONDS)
            show()
    finally:
        for worker in workers:
            worker.join()
    failed = [f"{i} (exit status {w.exitcode})" for i, w in enumerate(workers) if w.exitcode != 0]
    if failed:
        raise RuntimeError(f"worker process(es) failed: {', '.join(failed)}")


def best_entry(study: Study, optuna_study: optuna.Study) -> tuple[dict[str, Any], FrozenTrial] | None:
    """The zoo file content of the best trial (the entry trials started from, the tuned keys replaced),
    and that trial; None when no trial completed."""
    if not count(optuna_study, (TrialState.COMPLETE,)):
        return None
    best = optuna_study.best_trial
    entry = with_values(study.trials.entry, study.trials.space.values_of(best.params))
    return {study.trials.method.env_id: entry}, best


def write_best_entry(study: Study, optuna_study: optuna.Study) -> Path | None:
    """``<study>/best.yml``: the best trial's zoo entry, its comments naming the study and the trial;
    None when no trial completed."""
    found = best_entry(study, optuna_study)
    if found is None:
        return None
    content, best = found
    settings = study.trials
    finished = count(optuna_study, FINISHED)
    pruned = count(optuna_study, (TrialState.PRUNED,))
    window = min(WINDOW, settings.episodes)
    header = [
        f"The best trial of the Optuna study {study.name!r}",
        f"in {display_url(study.storage_url)}:",
        f"trial {best.number}, rolling success {best.value:.3f} over the last {window} of its "
        f"{settings.episodes} training episodes (seed {settings.seed});",
        f"{finished} trials finished, {pruned} of them pruned.",
        f"Run folder: {best.user_attrs.get('run_dir', '?')}",
        f"Search space: {Path(settings.space.source).resolve()}",
        *textwrap.wrap(f"Tuned keys: {', '.join(best.params)}.", 100, break_long_words=False),
        f"The rest is the {settings.method.env_id} entry trials started from.",
    ]
    path = settings.study_dir / BEST_FILE
    text = "".join(f"# {line}\n" for line in header)
    path.write_text(text + "\n" + yaml.safe_dump(content, sort_keys=False))
    return path
