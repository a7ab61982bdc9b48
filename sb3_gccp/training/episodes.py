"""The episode log of a training run: one CSV row per finished episode (``episodes.csv``).

The decider stage (through the GCCP callback) and the baselines write it in one layout, so that
``reproduce`` draws their training curves alike.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

EPISODE_FIELDS = ("episode", "timesteps", "task", "success", "crashed", "offroad", "timeout", "masks_on")
"""The columns of ``episodes.csv``."""


def episode_row(info: Mapping[str, Any], episode: int, timesteps: int, masks_on: bool) -> dict[str, Any]:
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
    }


def write_episodes(rows: list[dict[str, Any]], path: Path) -> None:
    """One CSV row per training episode."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=EPISODE_FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def read_episodes(path: Path) -> list[dict[str, Any]]:
    """The rows written by :func:`write_episodes` (numbers as ints)."""
    if not path.is_file():
        return []
    with path.open(newline="") as file:
        return [{k: v if k == "task" else int(v) for k, v in row.items()} for row in csv.DictReader(file)]


def rolling_rate(values: list[int], window: int = 100) -> np.ndarray:
    """Mean of the last ``window`` values (fewer at the start) at every episode."""
    array = np.asarray(values, dtype=float)
    if not len(array):
        return array
    sums = np.cumsum(array)
    counts = np.minimum(np.arange(1, len(array) + 1), window)
    previous = np.concatenate([np.zeros(window), sums])[: len(array)]
    return (sums - previous) / counts
