"""The episode log of a training run: one CSV row per finished episode (``episodes.csv``).

The decider stage (through the GCCP callback) and the baselines write it in one layout, so that
``reproduce`` draws their training curves alike.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

EPISODE_FIELDS = (
    "episode",
    "timesteps",
    "task",
    "success",
    "crashed",
    "offroad",
    "timeout",
    "masks_on",
    "wall_clock_s",
)
"""The columns of ``episodes.csv``. ``wall_clock_s``: seconds the run had trained for when the episode
ended (:class:`TrainingClock`); empty in rows whose run resumed from a log written without it."""


class TrainingClock:
    """Seconds a run has trained for, summed over the processes that trained it.

    A resumed run goes on from the time in the last row it resumed with; the work lost after that
    checkpoint is not counted. When that row has no time (a log written before the column), the
    run's time is unknown and the clock gives None.

    :param history: the rows the run resumed with (none for a new run)
    """

    def __init__(self, history: list[dict[str, Any]] | None = None) -> None:
        self._before: float | None = history[-1].get("wall_clock_s") if history else 0.0
        self._start = time.perf_counter()

    def __call__(self) -> float | None:
        if self._before is None:
            return None
        return self._before + time.perf_counter() - self._start


def episode_row(
    info: Mapping[str, Any], episode: int, timesteps: int, masks_on: bool, wall_clock_s: float | None = None
) -> dict[str, Any]:
    """One row of ``episodes.csv`` from the final ``info`` of an episode."""
    return {
        "episode": episode,
        "timesteps": timesteps,
        "task": info.get("task", ""),
        "success": int(bool(info.get("is_success"))),
        "crashed": int(bool(info.get("crashed"))),
        "offroad": int(bool(info.get("offroad"))),
        "timeout": int(bool(info.get("timeout"))),
        "masks_on": int(masks_on),
        "wall_clock_s": None if wall_clock_s is None else round(wall_clock_s, 1),
    }


def write_episodes(rows: list[dict[str, Any]], path: Path) -> None:
    """One CSV row per training episode."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=EPISODE_FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def read_episodes(path: Path) -> list[dict[str, Any]]:
    """The rows written by :func:`write_episodes`: counts as ints, ``wall_clock_s`` a float or None (also
    in a log written before that column)."""
    if not path.is_file():
        return []
    with path.open(newline="") as file:
        return [_parse_row(row) for row in csv.DictReader(file)]


def _parse_row(row: Mapping[str, str]) -> dict[str, Any]:
    parsed: dict[str, Any] = {k: v if k == "task" else int(v) for k, v in row.items() if k != "wall_clock_s"}
    clock = row.get("wall_clock_s")
    parsed["wall_clock_s"] = float(clock) if clock else None
    return parsed


def rolling_rate(values: list[int], window: int = 100) -> np.ndarray:
    """Mean of the last ``window`` values (fewer at the start) at every episode."""
    array = np.asarray(values, dtype=float)
    if not len(array):
        return array
    sums = np.cumsum(array)
    counts = np.minimum(np.arange(1, len(array) + 1), window)
    previous = np.concatenate([np.zeros(window), sums])[: len(array)]
    return (sums - previous) / counts
