"""Shared fixtures: an empty-road world with a hand-placed ego, the cached layout, hypothesis settings; the
SUMO networks and SMARTS scenarios the tests build go to a temporary folder, not the user's cache."""

from __future__ import annotations

import getpass
import os
import tempfile

# Offscreen pygame without audio (ALSA probing costs seconds on machines without a sound card).
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

from collections.abc import Callable, Iterator
from pathlib import Path
from subprocess import CompletedProcess
from typing import Any

import numpy as np
import pytest
import torch as th
from helpers import EMPTY
from hypothesis import HealthCheck, Phase, settings

import gccp_envs  # noqa: F401  (registers the environments)
from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import IntersectionLayout, layout_for
from gccp_envs.sumo.network import CACHE_VARIABLE
from gccp_envs.world import IntersectionWorld

_PHASES = [Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink]  # no slow "explain" phase
settings.register_profile(
    "gccp",
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    phases=_PHASES,
    suppress_health_check=[HealthCheck.too_slow],
)
# A longer random search: HYPOTHESIS_PROFILE=thorough python -m pytest -q
settings.register_profile(
    "thorough",
    max_examples=1000,
    deadline=None,
    database=None,
    phases=_PHASES,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "gccp"))


def pytest_configure(config: pytest.Config) -> None:
    """Build the tests' SUMO networks and SMARTS scenarios in a folder of the system's temporary folder (kept
    between runs, shared by the xdist workers, which inherit the variable), not in the user's cache, unless
    ``$GCCP_SUMO_CACHE`` names a folder already."""
    if not os.environ.get(CACHE_VARIABLE):
        folder = Path(tempfile.gettempdir()) / f"gccp_envs-tests-{getpass.getuser()}"
        os.environ[CACHE_VARIABLE] = str(folder / "sumo")


@pytest.fixture
def make_world() -> Callable[..., IntersectionWorld]:
    """Factory of reset worlds: ``make_world(task="left", seed=0, **config_overrides)``."""

    def make(task: str = "straight", seed: int = 0, **overrides: Any) -> IntersectionWorld:
        world = IntersectionWorld(EMPTY.replace(**overrides) if overrides else EMPTY)
        world.reset(np.random.default_rng(seed), task)
        return world

    return make


@pytest.fixture(scope="session")
def layout() -> IntersectionLayout:
    """The default two-lane junction (built once per process)."""
    return layout_for(IntersectionConfig())


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    """One torch thread per test: tiny networks gain nothing from two, and a busy machine makes them crawl."""
    threads = th.get_num_threads()
    th.set_num_threads(1)
    yield
    th.set_num_threads(threads)


@pytest.fixture
def cli(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> Callable[..., CompletedProcess[str]]:
    """``cli(*args, cwd=PATH)``: ``sb3_gccp ARGS`` run in this process from ``PATH``, its exit status and
    output as ``subprocess.run`` reports them. For commands that start no worker process: the seconds a
    fresh interpreter costs to import torch buy nothing there (``helpers.run_cli`` runs one)."""
    from sb3_gccp.cli import main

    def run(*args: str, cwd: Path) -> CompletedProcess[str]:
        monkeypatch.chdir(cwd)
        capsys.readouterr()
        try:
            status = main(list(args))
        except SystemExit as exit_:  # argparse's own usage errors
            status = exit_.code if isinstance(exit_.code, int) else 1
        out, err = capsys.readouterr()
        return CompletedProcess(["sb3_gccp", *args], status, out, err)

    return run


@pytest.fixture
def cli_error(cli: Callable[..., CompletedProcess[str]]) -> Callable[..., list[str]]:
    """``cli_error(cwd, *args)``: run ``sb3_gccp ARGS`` in this process, check that it exits with status 2,
    and return the lines it wrote to stderr."""

    def run(cwd: Path, *args: str) -> list[str]:
        result = cli(*args, cwd=cwd)
        assert result.returncode == 2, result.stderr
        return result.stderr.strip().splitlines()

    return run


FIRST = ("test_reproduce.py", "test_decider_stage.py", "test_planner_stage.py", "test_predictor_stage.py")
"""Modules whose tests run whole training stages: they are collected first, so that on two workers none of
them is left to run alone at the end of the test run."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Move the tests of :data:`FIRST` to the front, each module's tests in their order."""
    items.sort(key=lambda item: item.path.name not in FIRST)
