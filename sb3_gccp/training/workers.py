"""Worker processes: the fork server they start from, with the modules they need imported once."""

from __future__ import annotations

import multiprocessing
from multiprocessing.context import BaseContext


def start_worker_server(*modules: str) -> None:
    """Start multiprocessing's fork server now, with ``modules`` imported in it, so that the worker
    processes forked from it later (a ``SubprocVecEnv``'s, a labelling pool's) start without importing
    them each: about 4 s of torch, highway-env and ours a process, here once and beside the work of this
    one. Nothing happens where there is no fork server (the ``spawn`` start method) or once this process
    has one."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        from multiprocessing import forkserver

        forkserver.set_forkserver_preload(["__main__", *modules])  # __main__: multiprocessing's default
        forkserver.ensure_running()


def worker_context() -> BaseContext:
    """The start method of worker processes: ``forkserver`` (they do not inherit this process's torch
    state and threads), ``spawn`` where there is none."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
