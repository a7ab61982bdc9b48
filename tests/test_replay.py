"""The predictor's episode and replay buffers: decision points only, capacity, sampling, saving."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_gccp.gccp.replay import EpisodeReplayBuffer, collect_decisions, to_torch

STATE = {
    "history": ((6, 10, 9), np.float32),
    "history_mask": ((6, 10), np.float32),
    "routes": ((6, 3, 50, 8), np.float32),
    "routes_mask": ((6, 3, 50), np.float32),
    "bev": ((1, 64, 64), np.uint8),
}


def fake_decision(number: int) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """A decision whose every array holds ``number`` (masks: its parity), with decider-only keys too."""
    obs = {
        key: np.full(shape, number if "mask" not in key else number % 2, dtype)
        for key, (shape, dtype) in STATE.items()
    }
    obs["subgoals"] = np.full((12, 3), number, np.float32)
    obs["task_goal"] = np.zeros(3, np.float32)
    return (
        obs,
        np.full(3, number, np.float32),
        np.full((6, 10, 3), number, np.float32),
        np.ones((6, 10), bool),
    )


def fill(buffer: EpisodeReplayBuffer, episodes: list[list[int]]) -> None:
    for episode in episodes:
        for number in episode:
            buffer.add(*fake_decision(number))
        buffer.end_episode()


def numbers(buffer: EpisodeReplayBuffer) -> list[int]:
    return [int(value) for value in buffer.stored()["subgoal"][:, 0]]


class RecordingWrapper(gym.Wrapper):
    """Records the observation before every step, the action and the step's info."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.records: list[tuple[dict[str, np.ndarray], int, dict[str, Any]]] = []
        self._obs: dict[str, np.ndarray] = {}

    def reset(self, **kwargs):
        self._obs, info = self.env.reset(**kwargs)
        return self._obs, info

    def step(self, action):
        before = self._obs
        self._obs, reward, terminated, truncated, info = self.env.step(action)
        self.records.append((before, int(action), info))
        return self._obs, reward, terminated, truncated, info


@pytest.fixture(scope="module")
def collected() -> tuple[EpisodeReplayBuffer, RecordingWrapper, int]:
    env = RecordingWrapper(gym.make("GCCPDecider-v0", spawn_probability=0.3, duration=8.0))
    rng = np.random.default_rng(0)
    buffer = EpisodeReplayBuffer(capacity=1000)
    stored = collect_decisions(env, lambda obs, mask: int(rng.integers(12)), 2, buffer, rng)
    return buffer, env, stored


def test_collect_stores_every_decision_point_and_nothing_else(collected):
    buffer, env, stored = collected
    assert stored == len(buffer) == len(env.records) >= 10  # one entry per decider step, not per T_m steps
    assert not buffer.episode
    data = buffer.stored()
    assert set(data) == {
        "history",
        "history_mask",
        "routes",
        "routes_mask",
        "bev",
        "subgoal",
        "future",
        "future_mask",
    }
    for i, (obs, action, info) in enumerate(env.records):
        for key in ("history", "history_mask", "routes", "routes_mask", "bev"):
            np.testing.assert_array_equal(data[key][i], obs[key], err_msg=key)
        np.testing.assert_array_equal(data["subgoal"][i], obs["subgoals"][action])
        np.testing.assert_array_equal(data["future"][i], info["future"])
        np.testing.assert_array_equal(data["future_mask"][i], info["future_mask"])
    assert data["future_mask"][:, 0].any() and data["future_mask"][:, 1:].any()


def test_collect_passes_the_env_mask_to_the_chooser():
    env = gym.make("GCCPDecider-v0", spawn_probability=0.0, duration=2.0)
    env.unwrapped.set_mask_fn(lambda obs: np.arange(12) == 4)
    seen: list[np.ndarray] = []

    def choose(obs, mask):
        seen.append(mask)
        return int(np.flatnonzero(mask)[0])

    buffer = EpisodeReplayBuffer()
    stored = collect_decisions(env, choose, 1, buffer, np.random.default_rng(0), progress=True)
    assert stored == len(seen) == 2  # a 2 s episode holds two decisions of T_m = 1 s
    assert all((mask == (np.arange(12) == 4)).all() for mask in seen)


def test_decisions_reach_the_replay_buffer_at_the_end_of_the_episode():
    buffer = EpisodeReplayBuffer(capacity=10)
    buffer.add(*fake_decision(1))
    buffer.add(*fake_decision(2))
    assert len(buffer) == 0
    assert buffer.end_episode() == 2
    assert len(buffer) == 2 and numbers(buffer) == [1, 2]
    assert buffer.end_episode() == 0 and len(buffer) == 2


def test_capacity_keeps_the_newest_decisions():
    buffer = EpisodeReplayBuffer(capacity=5)
    fill(buffer, [[0, 1, 2], [3, 4, 5], [6]])
    assert len(buffer) == 5 and numbers(buffer) == [2, 3, 4, 5, 6]
    fill(buffer, [list(range(10, 18))])  # an episode longer than the capacity
    assert numbers(buffer) == [13, 14, 15, 16, 17]
    assert all(len(array) == 5 for array in buffer.arrays.values())


def test_latest_are_the_newest_decisions_oldest_first():
    buffer = EpisodeReplayBuffer(capacity=5)
    fill(buffer, [[0, 1, 2], [3, 4, 5], [6]])  # wrapped around the ring
    latest = buffer.latest(3)
    stored = buffer.stored()
    assert all(np.array_equal(latest[key], stored[key][-3:]) for key in stored)
    assert len(buffer.latest(50)["future"]) == 5


def test_sample_shapes_dtypes_and_uniformity():
    buffer = EpisodeReplayBuffer(capacity=8)
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(4, np.random.default_rng(0))
    fill(buffer, [[0, 1, 2], [3]])
    batch = buffer.sample(64, np.random.default_rng(0))
    for key, (shape, dtype) in STATE.items():
        assert batch[key].shape == (64, *shape) and batch[key].dtype == dtype, key
    assert batch["subgoal"].shape == (64, 3)
    assert batch["future"].shape == (64, 6, 10, 3) and batch["future_mask"].dtype == bool
    drawn = batch["subgoal"][:, 0]
    assert set(drawn.astype(int)) == {0, 1, 2, 3}
    np.testing.assert_array_equal(batch["history_mask"][:, 0, 0], drawn % 2)
    np.testing.assert_array_equal(buffer.sample(64, np.random.default_rng(0))["subgoal"], batch["subgoal"])
    tensors = to_torch(batch)
    assert tensors["history"].dtype == th.float32 and tensors["future_mask"].dtype == th.bool
    assert tensors["bev"].dtype == th.uint8 and tensors["routes_mask"].dtype == th.float32


def test_save_and_load_round_trip(tmp_path):
    buffer = EpisodeReplayBuffer(capacity=4)
    fill(buffer, [[0, 1, 2], [3, 4]])  # wrapped around the ring
    path = tmp_path / "replay.npz"
    buffer.save(path)
    loaded = EpisodeReplayBuffer.load(path)
    assert loaded.capacity == 4 and len(loaded) == 4
    for key, value in buffer.stored().items():
        np.testing.assert_array_equal(loaded.stored()[key], value, err_msg=key)
        assert loaded.stored()[key].dtype == value.dtype
    fill(loaded, [[5]])
    assert numbers(loaded) == [2, 3, 4, 5]
    assert numbers(EpisodeReplayBuffer.load(path, capacity=2)) == [3, 4]
    EpisodeReplayBuffer(capacity=3).save(tmp_path / "empty.npz")
    empty = EpisodeReplayBuffer.load(tmp_path / "empty.npz")
    assert len(empty) == 0 and empty.capacity == 3
