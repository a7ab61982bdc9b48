"""One SUMO instance: libsumo inside this process when it is free, else a ``sumo`` process over TraCI.

libsumo runs SUMO in the calling process at the cost of a function call per query, but a process holds
one libsumo simulation at most; a second env in the same process (a ``DummyVecEnv``) gets its own
``sumo`` process, driven over a TraCI socket. Both offer the same API (``api.vehicle.add``,
``api.simulationStep``, ...). Closing the instance, or losing the last reference to it, ends it and its
process.
"""

from __future__ import annotations

import contextlib
import subprocess
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from importlib.util import find_spec
from typing import Any

_libsumo_taken = False
"""Whether an instance of this process runs in libsumo (it holds one simulation at most)."""


def libsumo_free() -> bool:
    """Whether a new instance can run in this process through libsumo."""
    return not _libsumo_taken and find_spec("libsumo") is not None


def _release_libsumo() -> None:
    global _libsumo_taken
    _libsumo_taken = False


@contextmanager
def closing_on_error(close: Callable[[], None]) -> Iterator[None]:
    """Call ``close`` if the block raises, then raise on: an env may never be closed after an exception,
    and no simulation may outlive it."""
    try:
        yield
    except BaseException:
        close()
        raise


class SumoSimulation:
    """A running SUMO simulation.

    :param args: SUMO's command-line options (without the binary)
    """

    def __init__(self, args: Sequence[str]) -> None:
        global _libsumo_taken
        import sumolib

        binary = sumolib.checkBinary("sumo")
        self.process: subprocess.Popen[bytes] | None = None
        """The ``sumo`` process when SUMO runs outside this process (TraCI)."""
        if libsumo_free():
            import libsumo

            _libsumo_taken = True
            try:
                libsumo.start([binary, *args])
            except BaseException:
                _release_libsumo()
                raise
            self.api: Any = libsumo
        else:
            self.api, self.process = _start_traci(binary, args)
        self.in_process = self.process is None
        """Whether SUMO runs inside this process (libsumo)."""
        self._finalizer = weakref.finalize(self, _shutdown, self.api, self.process, self.in_process)

    def load(self, args: Sequence[str]) -> None:
        """Restart the simulation with new options (a new seed), keeping the process."""
        self.api.load(list(args))

    def close(self) -> None:
        """End the simulation and its process (a second call does nothing)."""
        self._finalizer()


def _start_traci(binary: str, args: Sequence[str], attempts: int = 3) -> tuple[Any, subprocess.Popen[bytes]]:
    """A ``sumo`` process listening on a free port, and the TraCI connection to it.

    A port found free can be taken by another process before SUMO binds it (SUMO then exits): then try
    another.
    """
    import traci
    from sumolib.miscutils import getFreeSocketPort

    error: Exception | None = None
    for _ in range(attempts):
        port = getFreeSocketPort()
        process = subprocess.Popen(
            [binary, "--remote-port", str(port), *args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            return _connect(port, process), process
        except (traci.TraCIException, traci.FatalTraCIError) as err:
            _end_process(process, timeout=0.0)
            error = err
    raise RuntimeError(f"could not connect to SUMO over TraCI: {error}")


def _connect(port: int, process: subprocess.Popen[bytes], timeout: float = 30.0) -> Any:
    """Connect to a starting SUMO, retrying quietly (TraCI's own retries print to stdout)."""
    import traci

    deadline = time.monotonic() + timeout
    while True:
        try:
            return traci.connect(port, numRetries=0, proc=process)
        except traci.FatalTraCIError:  # not listening yet (TraCIException: the process has ended)
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def _shutdown(api: Any, process: subprocess.Popen[bytes] | None, in_process: bool) -> None:
    """End a simulation whatever state it is in: close it, then make sure its process is gone."""
    with contextlib.suppress(Exception):  # a simulation that failed may not close cleanly: it ends anyway
        if in_process:
            api.close()
        else:
            api.close(wait=False)
    if process is not None:
        _end_process(process)
    if in_process:
        _release_libsumo()


def _end_process(process: subprocess.Popen[bytes], timeout: float = 5.0) -> None:
    """Wait for a process to exit after its connection closed; kill it if it does not."""
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
