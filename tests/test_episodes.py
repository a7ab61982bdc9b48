"""The episode log: rows from an episode's final info, the CSV round trip, rolling rates."""

from __future__ import annotations

import numpy as np

from sb3_gccp.training.episodes import (
    EPISODE_FIELDS,
    TrainingClock,
    episode_row,
    read_episodes,
    rolling_rate,
    write_episodes,
)


def test_episode_rows_round_trip_through_the_csv(tmp_path):
    rows = [
        episode_row({"task": "left", "is_success": True}, 1, 300, masks_on=False),
        episode_row(
            {"task": "right", "crashed": True, "timeout": False}, 2, 420, masks_on=True, wall_clock_s=3.14
        ),
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
        "wall_clock_s": 3.1,
    }
    assert rows[0]["wall_clock_s"] is None  # unknown: written empty, read back as None
    write_episodes(rows, tmp_path / "episodes.csv")
    assert read_episodes(tmp_path / "episodes.csv") == rows
    assert read_episodes(tmp_path / "missing.csv") == []


def test_rolling_rate_averages_the_last_window_of_episodes():
    np.testing.assert_allclose(rolling_rate([1, 0, 1, 1], window=2), [1.0, 0.5, 0.5, 1.0])
    np.testing.assert_allclose(rolling_rate([0, 1, 1], window=100), [0.0, 0.5, 2 / 3])
    assert len(rolling_rate([])) == 0


def test_a_log_written_before_the_wall_clock_column_reads_with_an_unknown_time(tmp_path):
    path = tmp_path / "episodes.csv"
    path.write_text("episode,timesteps,task,success,crashed,offroad,timeout,masks_on\n1,32,right,0,1,0,0,0\n")
    rows = read_episodes(path)
    assert rows == [{**episode_row({"task": "right", "crashed": True}, 1, 32, False), "wall_clock_s": None}]
    assert TrainingClock(rows)() is None  # a run resumed from it cannot know its time


def test_the_training_clock_goes_on_from_the_run_it_resumes(monkeypatch):
    now = [100.0]
    monkeypatch.setattr("sb3_gccp.training.episodes.time.perf_counter", lambda: now[0])
    fresh, resumed = TrainingClock(), TrainingClock([{"wall_clock_s": 10.0}, {"wall_clock_s": 600.0}])
    now[0] = 130.0
    assert fresh() == 30.0 and resumed() == 630.0
