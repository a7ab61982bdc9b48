"""DQN with action masks: SB3's DQN whose Q-values of masked actions are never taken or bootstrapped.

The mask comes in the observation (:mod:`sb3_gccp.action_masks`; wrap the env in
:class:`~sb3_gccp.action_masks.ActionMaskObservation`). The Q-network sets a masked action's value to
a huge negative number, so the greedy action, the TD target's max over the next state's actions and
the evaluation all range over the allowed actions only; the loss reads only the taken (allowed)
actions' values. Epsilon-greedy and warm-up actions are drawn uniformly from the allowed actions.
Without a mask in the observation it is SB3's DQN.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import CombinedExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork

from sb3_gccp.action_masks import MaskedRandomActions, mask_values, random_allowed_actions


class MaskedQNetwork(QNetwork):
    """SB3's Q-network with the masked actions' values replaced by :data:`~sb3_gccp.action_masks.HUGE_NEG`."""

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """Q-values of every action, masked ones at a huge negative value.

        :param obs: a batch of observations, with or without an action mask
        :return: (B, n_actions)
        """
        return mask_values(super().forward(obs), obs)


class MaskableDQNPolicy(DQNPolicy):
    """SB3's DQN policy on :class:`MaskedQNetwork` (online and target network)."""

    def make_q_net(self) -> QNetwork:
        net_args = self._update_features_extractor(self.net_args, features_extractor=None)
        return MaskedQNetwork(**net_args).to(self.device)


class MaskableMultiInputPolicy(MaskableDQNPolicy):
    """:class:`MaskableDQNPolicy` for Dict observations (SB3's ``CombinedExtractor`` by default)."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        kwargs.setdefault("features_extractor_class", CombinedExtractor)
        super().__init__(*args, **kwargs)


class MaskableDQN(MaskedRandomActions, DQN):
    """SB3's DQN with action masks read from the observation (see the module's docstring).

    Takes every :class:`~stable_baselines3.DQN` argument.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MaskableDQNPolicy,
        "MultiInputPolicy": MaskableMultiInputPolicy,
    }

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """Epsilon-greedy over the allowed actions (greedy when ``deterministic``)."""
        if deterministic or np.random.rand() >= self.exploration_rate:
            return self.policy.predict(observation, state, episode_start, deterministic)
        vectorized = self.policy.is_vectorized_observation(observation)
        batch = {k: np.asarray(v) for k, v in observation.items()} if isinstance(observation, dict) else {}
        if not vectorized:
            batch = {k: v[None] for k, v in batch.items()}
        first = next(iter(batch.values())) if batch else np.asarray(observation)[None]
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        action = random_allowed_actions(batch, n_actions, len(first))
        return (action if vectorized else action[0]), state
