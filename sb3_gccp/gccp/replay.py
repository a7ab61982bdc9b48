"""The predictor's episode buffer D_e and replay buffer D (paper III-E, Algorithm 1).

Every decision point (t mod T_m = 0) of an episode is added to the episode buffer: the environment
state s_t, the subgoal the decision-maker chose and the ground-truth future of the ego and of the
neighbours of s_t (``info["future"]`` and ``info["future_mask"]`` of the decider env's step). At the
end of the episode they move into the replay buffer, a ring of preallocated numpy arrays that keeps
the latest ``capacity`` decisions and from which the predictor samples uniform batches.

Only the state keys are stored, not the decider's 12 candidates or its task goal: the predictor
reads the chosen subgoal only. Masks are stored as bool and handed out as float32 like the
observation's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

from sb3_gccp.gccp.predictor import STATE_KEYS
from sb3_gccp.progress import new_bar
from sb3_gccp.safe_loading import first_line

MASK_KEYS = ("history_mask", "routes_mask")
"""State keys holding 0/1 masks, stored as bool."""

Decision = dict[str, np.ndarray]
Chooser = Callable[[dict[str, np.ndarray], np.ndarray], int]
"""A decision-maker: (decider observation, action mask) -> subgoal index."""


class EpisodeReplayBuffer:
    """Episode buffer D_e and replay buffer D of the predictor's training data (decision points only).

    :param capacity: decisions kept in the replay buffer; the oldest are overwritten first
    """

    def __init__(self, capacity: int = 20_000) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.capacity = capacity
        self.episode: list[Decision] = []
        self.arrays: dict[str, np.ndarray] = {}
        self.position = 0
        self.full = False

    def __len__(self) -> int:
        """Decisions in the replay buffer (the current episode's are not counted until it ends)."""
        return self.capacity if self.full else self.position

    def add(
        self,
        obs: Mapping[str, np.ndarray],
        subgoal: np.ndarray,
        future: np.ndarray,
        future_mask: np.ndarray,
    ) -> None:
        """Add one decision point to the episode buffer.

        :param obs: the decider observation at the decision (its state keys are kept, copied)
        :param subgoal: (3,) the chosen subgoal (x, y, heading) in the ego frame of ``obs``
        :param future: (V, T_f, 3) ground-truth poses of the vehicles of ``obs`` after the decision
        :param future_mask: (V, T_f) which of them exist
        """
        decision = {key: np.array(obs[key], dtype=bool if key in MASK_KEYS else None) for key in STATE_KEYS}
        decision["subgoal"] = np.array(subgoal, dtype=np.float32)
        decision["future"] = np.array(future, dtype=np.float32)
        decision["future_mask"] = np.array(future_mask, dtype=bool)
        self.episode.append(decision)

    def end_episode(self) -> int:
        """Move the episode buffer into the replay buffer.

        :return: the number of decisions moved
        """
        episode, self.episode = self.episode, []
        if episode:
            self._write({key: np.stack([decision[key] for decision in episode]) for key in episode[0]})
        return len(episode)

    def _write(self, decisions: Mapping[str, np.ndarray]) -> None:
        """Put decisions (arrays with a leading decision axis, oldest first) into the ring."""
        if not self.arrays:
            self.arrays = {
                key: np.zeros((self.capacity, *value.shape[1:]), value.dtype)
                for key, value in decisions.items()
            }
        kept = {key: value[-self.capacity :] for key, value in decisions.items()}
        count = len(kept["future"])
        rows = (self.position + np.arange(count)) % self.capacity
        for key, array in self.arrays.items():
            array[rows] = kept[key]
        self.full |= self.position + count >= self.capacity
        self.position = int(rows[-1] + 1) % self.capacity

    def _order(self) -> np.ndarray:
        """Rows of the stored decisions, oldest first."""
        return np.roll(np.arange(self.capacity), -self.position) if self.full else np.arange(self.position)

    def stored(self) -> dict[str, np.ndarray]:
        """Every decision in the replay buffer, oldest first (masks as float32).

        :return: arrays with a leading axis of length ``len(self)``
        """
        return self._get(self._order())

    def latest(self, count: int) -> dict[str, np.ndarray]:
        """The newest ``count`` decisions (all if fewer), oldest first (masks as float32)."""
        return self._get(self._order()[-count:])

    def sample(self, batch_size: int = 64, rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
        """A batch of decisions drawn uniformly with replacement.

        :param batch_size: N_b (paper: 64)
        :param rng: the random generator (default: a fresh unseeded one)
        :return: arrays with a leading axis of length ``batch_size`` (masks as float32)
        """
        if not len(self):
            raise ValueError("the replay buffer is empty")
        rng = rng or np.random.default_rng()
        return self._get(rng.integers(len(self), size=batch_size))

    def _get(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        return {
            key: array[rows].astype(np.float32) if key in MASK_KEYS else array[rows]
            for key, array in self.arrays.items()
        }

    def save(self, path: str | Path) -> None:
        """Write the replay buffer (oldest first, with its capacity) to one compressed ``.npz`` file.

        :param path: the file to write
        """
        order = self._order()
        stored = {key: array[order] for key, array in self.arrays.items()}
        np.savez_compressed(path, capacity=np.array(self.capacity), **stored)

    @classmethod
    def load(cls, path: str | Path, capacity: int | None = None) -> EpisodeReplayBuffer:
        """Read a replay buffer written by :meth:`save`.

        :param path: the ``.npz`` file
        :param capacity: capacity of the new buffer (default: the saved one); a smaller one keeps the newest
        :return: the buffer
        :raises ValueError: one line, when the file is no replay buffer written by :meth:`save`
        """
        try:
            with np.load(path) as saved:
                buffer = cls(int(saved["capacity"]) if capacity is None else capacity)
                stored = {key: saved[key] for key in saved.files if key != "capacity"}
            if stored and len(stored["future"]):
                buffer._write(stored)
        except Exception as err:  # numpy's reader, a missing array and a bad shape raise many kinds
            raise ValueError(f"{path} is not a replay buffer saved by sb3_gccp: {first_line(err)}") from err
        return buffer


def to_torch(batch: Mapping[str, np.ndarray], device: str | th.device = "cpu") -> dict[str, th.Tensor]:
    """Tensors of a batch (``future_mask`` bool, ``bev`` uint8, the rest float32).

    :param batch: numpy arrays, e.g. from :meth:`EpisodeReplayBuffer.sample`
    :param device: where to put them
    :return: the tensors, sharing memory with ``batch`` on the CPU
    """
    return {key: th.as_tensor(value, device=device) for key, value in batch.items()}


def collect_decisions(
    env: gym.Env,
    choose: Chooser,
    episodes: int,
    buffer: EpisodeReplayBuffer,
    rng: np.random.Generator,
    progress: bool = False,
) -> int:
    """Run decider episodes and store every decision point in ``buffer`` (Algorithm 1's D_e -> D).

    :param env: a ``GCCPDecider-v0`` env (possibly wrapped)
    :param choose: picks a subgoal index from the observation and the env's action mask
    :param episodes: how many episodes to run
    :param buffer: where the decisions go
    :param rng: seeds each episode's reset
    :param progress: show a tqdm progress bar over the episodes
    :return: the number of decisions stored
    """
    action_masks = env.unwrapped.action_masks  # type: ignore[attr-defined]
    stored = 0
    for _ in new_bar(range(episodes), enabled=progress, desc="episodes", unit="ep"):
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        done = False
        while not done:
            index = int(choose(obs, action_masks()))
            next_obs, _, terminated, truncated, info = env.step(index)
            buffer.add(obs, obs["subgoals"][index], info["future"], info["future_mask"])
            obs, done = next_obs, terminated or truncated
        stored += buffer.end_episode()
    return stored
