"""The episode log: rows from an episode's final info, the CSV round trip, rolling rates."""

from __future__ import annotations

import numpy as np

from sb3_gccp.training.episodes import (
    EPISODE_FIELDS,
    episode_row,
    read_episodes,
    rolling_rate,
    write_episodes,
)


def test_episode_rows_round_trip_through_the_csv(tmp_path):
    rows = [
        episode_row({"task": "left", "is_success": True}, 1, 300, masks_on=False),
        episode_row({"task": "right", "crashed": True, "timeout": False}, 2, 420, masks_on=True),
    ]
    assert list(rows[0]) == list(EPISODE_FIELDS)
    assert rows[1] == {
        "episode": 2,
        "timesteps": 420,
        "task": "right",
        "success": 0,
        "crashed": 1,
        "offroad": 0,
        "timeout": 0,
        "masks_on": 1,
    }
    write_episodes(rows, tmp_path / "episodes.csv")
    assert read_episodes(tmp_path / "episodes.csv") == rows
    assert read_episodes(tmp_path / "missing.csv") == []


def test_rolling_rate_averages_the_last_window_of_episodes():
    np.testing.assert_allclose(rolling_rate([1, 0, 1, 1], window=2), [1.0, 0.5, 0.5, 1.0])
    np.testing.assert_allclose(rolling_rate([0, 1, 1], window=100), [0.0, 0.5, 2 / 3])
    assert len(rolling_rate([])) == 0
