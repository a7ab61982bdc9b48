"""Action masks for off-policy algorithms (DQN, SAC-Discrete), carried in the observation.

MaskablePPO reads an env's ``action_masks()`` at every step and keeps the masks beside its rollout. An
off-policy algorithm also needs the masks of the *next* states of its replay samples (the greedy or
soft value of a state counts only its allowed actions), so here the mask travels in the observation:
:class:`ActionMaskObservation` adds it under :data:`ACTION_MASK_KEY`, the replay buffer stores it with
both observations, and the networks read it from there. The features extractors ignore the key.

The rule is sb3-contrib's (``MaskableCategorical``): a masked action's logit or Q-value is replaced by
:data:`HUGE_NEG`, so it is never the argmax and has probability zero, and the sums over actions stay
finite. Random actions (DQN's warm-up and epsilon steps, SAC-Discrete's warm-up) are drawn uniformly
from the allowed ones.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces

ACTION_MASK_KEY = "action_mask"
"""The observation key of the action mask (1: allowed)."""
HUGE_NEG = -1e8
"""Logit or Q-value of a masked action (sb3-contrib's value)."""


class ActionMaskObservation(gym.ObservationWrapper):
    """Adds the env's ``action_masks()`` to its Dict observation under :data:`ACTION_MASK_KEY` (a 0/1
    ``Box`` of int8, which SB3 stores as it is and the safe loader reads back from a model file).

    :param env: an env with a Dict observation space, a Discrete action space and ``action_masks()``
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        if not isinstance(env.observation_space, spaces.Dict) or not isinstance(
            env.action_space, spaces.Discrete
        ):
            raise ValueError(
                f"ActionMaskObservation needs a Dict observation and Discrete actions, got "
                f"{env.observation_space} and {env.action_space}"
            )
        n_actions = int(env.action_space.n)
        self.observation_space = spaces.Dict(
            {**env.observation_space.spaces, ACTION_MASK_KEY: spaces.Box(0, 1, (n_actions,), np.int8)}
        )

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        """The observation with the mask of the state it describes."""
        mask = np.asarray(self.env.unwrapped.action_masks(), dtype=np.int8)  # type: ignore[attr-defined]
        return {**observation, ACTION_MASK_KEY: mask}


def observes_masks(observation_space: spaces.Space) -> bool:
    """Whether observations of this space carry an action mask."""
    return isinstance(observation_space, spaces.Dict) and ACTION_MASK_KEY in observation_space.spaces


def mask_values(values: th.Tensor, observations: Any) -> th.Tensor:
    """``values`` (B, n_actions) with the masked actions' entries set to :data:`HUGE_NEG`; unchanged
    when the observations carry no mask."""
    if not isinstance(observations, dict) or ACTION_MASK_KEY not in observations:
        return values
    allowed = observations[ACTION_MASK_KEY].reshape(values.shape).bool()
    return th.where(allowed, values, th.full_like(values, HUGE_NEG))


def random_allowed_actions(observation: Any, n_actions: int, n_batch: int) -> np.ndarray:
    """One action per batch row, uniform over the row's allowed actions (over all without a mask).

    :param observation: a batch of observations (a dict of arrays with a leading batch axis)
    :param n_actions: number of discrete actions
    :param n_batch: rows in the batch
    :return: (n_batch,) actions
    """
    if isinstance(observation, dict) and ACTION_MASK_KEY in observation:
        allowed = np.asarray(observation[ACTION_MASK_KEY], dtype=bool).reshape(n_batch, n_actions)
    else:
        allowed = np.ones((n_batch, n_actions), dtype=bool)
    # Never all False (an env's mask always allows something); guard anyway.
    allowed[~allowed.any(axis=1)] = True
    weights = allowed / allowed.sum(axis=1, keepdims=True)
    return np.array([np.random.choice(n_actions, p=row) for row in weights])


class MaskedRandomActions:
    """Mixin for an off-policy algorithm on Discrete actions: warm-up actions drawn from the allowed ones.

    SB3 draws warm-up actions with ``action_space.sample()``, which ignores masks; this draws from the
    mask in ``_last_obs`` instead. Without masks in the observations it is SB3's draw.
    """

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        masked = observes_masks(self.observation_space)  # type: ignore[attr-defined]
        if masked and self.num_timesteps < learning_starts:  # type: ignore[attr-defined]
            action = random_allowed_actions(self._last_obs, int(self.action_space.n), n_envs)  # type: ignore[attr-defined]
            return action, action
        return super()._sample_action(learning_starts, action_noise, n_envs)  # type: ignore[misc]
