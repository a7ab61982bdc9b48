"""Policies of SAC-Discrete: a categorical actor and twin critics giving Q(s, a) for every action at once.

Unlike SB3's continuous SAC, the critics take no action input: with a finite action set every Q-value
of a state comes out of one forward pass, which is what makes the exact expectations over the actions
of :class:`~sb3_gccp.sac_discrete.SACDiscrete` cheap.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    NatureCNN,
    create_mlp,
    get_actor_critic_arch,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_gccp.action_masks import mask_values

DEFAULT_NET_ARCH = [256, 256]
"""Hidden layers of the actor and of each critic when ``net_arch`` is not given (SB3 SAC's default)."""


class Actor(BasePolicy):
    """Categorical policy pi(a|s): features, an MLP, one logit per discrete action.

    :param observation_space: observation space
    :param action_space: the discrete actions
    :param net_arch: hidden layers of the MLP
    :param features_extractor: the features extractor (possibly the critic's)
    :param features_dim: width of its features
    :param activation_fn: activation after every hidden layer
    :param normalize_images: whether to divide image observations by 255
    :param share_features_extractor: whether ``features_extractor`` is the critic's; then only the critic's
        loss trains it and the actor reads its features without gradient
    """

    action_space: spaces.Discrete

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        share_features_extractor: bool = False,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
        )
        self.share_features_extractor = share_features_extractor
        self.logits_net = nn.Sequential(
            *create_mlp(features_dim, int(action_space.n), net_arch, activation_fn)
        )

    def action_log_probs(self, obs: PyTorchObs) -> th.Tensor:
        """log pi(a|s) of every action: a masked softmax when the observations carry action masks
        (:mod:`sb3_gccp.action_masks`; a masked action's log-probability is about -1e8).

        :param obs: a batch of observations
        :return: (B, n_actions) log-probabilities
        """
        with th.set_grad_enabled(th.is_grad_enabled() and not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        return th.log_softmax(mask_values(self.logits_net(features), obs), dim=-1)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Actions for a batch of observations: the most probable one, or one sampled from pi(.|s).

        :param obs: a batch of observations
        :param deterministic: take the argmax instead of sampling
        :return: (B,) action indices
        """
        log_probs = self.action_log_probs(obs)
        if deterministic:
            return log_probs.argmax(dim=-1)
        return th.distributions.Categorical(logits=log_probs).sample()

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


class DiscreteCritic(BaseModel):
    """``n_critics`` Q-networks over shared features, each giving Q(s, a) for all actions.

    :param observation_space: observation space
    :param action_space: the discrete actions
    :param net_arch: hidden layers of each Q-network
    :param features_extractor: the features extractor (trained by the critic loss, also when shared)
    :param features_dim: width of its features
    :param activation_fn: activation after every hidden layer
    :param normalize_images: whether to divide image observations by 255
    :param n_critics: number of Q-networks (two: clipped double Q-learning)
    """

    action_space: spaces.Discrete
    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
        )
        n_actions = int(action_space.n)
        self.n_critics = n_critics
        self.q_networks = nn.ModuleList(
            nn.Sequential(*create_mlp(features_dim, n_actions, net_arch, activation_fn))
            for _ in range(n_critics)
        )

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """Every critic's Q-values of every action.

        :param obs: a batch of observations
        :return: (n_critics, B, n_actions)
        """
        features = self.extract_features(obs, self.features_extractor)
        return th.stack([q_net(features) for q_net in self.q_networks])


class SACDiscretePolicy(BasePolicy):
    """Actor, critics and target critics of SAC-Discrete, with their optimisers.

    :param observation_space: observation space
    :param action_space: the discrete actions
    :param lr_schedule: learning rate schedule (the optimisers start at ``lr_schedule(1)``)
    :param net_arch: hidden layers of the actor and of each critic: a list for both, or
        ``{"pi": [...], "qf": [...]}`` (default :data:`DEFAULT_NET_ARCH`)
    :param activation_fn: activation after every hidden layer
    :param features_extractor_class: features extractor, e.g.
        :class:`~sb3_gccp.policies.PlannerFeaturesExtractor` for the intersection envs
    :param features_extractor_kwargs: its keyword arguments
    :param normalize_images: whether to divide image observations by 255
    :param optimizer_class: optimiser of the actor and of the critics
    :param optimizer_kwargs: its keyword arguments besides the learning rate
    :param n_critics: number of Q-networks
    :param share_features_extractor: one features extractor for the actor and the critics, trained by
        the critic loss only (as in SAC-AE, https://arxiv.org/abs/1910.01741; SB3's SAC trains a shared
        one with the actor loss). The target critics always keep their own copy.
    """

    actor: Actor
    critic: DiscreteCritic
    critic_target: DiscreteCritic
    action_space: spaces.Discrete

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 2,
        share_features_extractor: bool = False,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=normalize_images,
        )
        self.net_arch = net_arch if net_arch is not None else list(DEFAULT_NET_ARCH)
        self.activation_fn = activation_fn
        self.n_critics = n_critics
        self.share_features_extractor = share_features_extractor
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        actor_arch, critic_arch = get_actor_critic_arch(self.net_arch)
        self.critic = self.make_critic(critic_arch)
        self.critic_target = self.make_critic(critic_arch)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.set_training_mode(False)
        shared = self.critic.features_extractor if self.share_features_extractor else None
        self.actor = self.make_actor(actor_arch, shared)
        actor_parameters = [
            param
            for name, param in self.actor.named_parameters()
            if not (self.share_features_extractor and name.startswith("features_extractor."))
        ]
        self.actor.optimizer = self.optimizer_class(
            actor_parameters, lr=lr_schedule(1), **self.optimizer_kwargs  # type: ignore[call-arg]
        )
        self.critic.optimizer = self.optimizer_class(
            self.critic.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs  # type: ignore[call-arg]
        )

    def make_actor(
        self, net_arch: list[int], features_extractor: BaseFeaturesExtractor | None = None
    ) -> Actor:
        """A new actor, on ``features_extractor`` or on a new features extractor."""
        kwargs = self._update_features_extractor(self._net_kwargs(net_arch), features_extractor)
        return Actor(**kwargs, share_features_extractor=features_extractor is not None).to(self.device)

    def make_critic(self, net_arch: list[int]) -> DiscreteCritic:
        """New critics on a new features extractor."""
        kwargs = self._update_features_extractor(self._net_kwargs(net_arch))
        return DiscreteCritic(**kwargs, n_critics=self.n_critics).to(self.device)

    def _net_kwargs(self, net_arch: list[int]) -> dict[str, Any]:
        return {
            "observation_space": self.observation_space,
            "action_space": self.action_space,
            "net_arch": net_arch,
            "activation_fn": self.activation_fn,
            "normalize_images": self.normalize_images,
        }

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            n_critics=self.n_critics,
            share_features_extractor=self.share_features_extractor,
            lr_schedule=self._dummy_schedule,  # loading the policy alone needs no optimiser schedule
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """The actor's actions (see :meth:`Actor.forward`)."""
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.actor(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        """Training or evaluation mode of the actor and the critics (batch norm, dropout).

        :param mode: ``True`` for training mode
        """
        self.actor.set_training_mode(mode)
        self.critic.set_training_mode(mode)
        self.training = mode


MlpPolicy = SACDiscretePolicy


class CnnPolicy(SACDiscretePolicy):
    """:class:`SACDiscretePolicy` over image observations: SB3's ``NatureCNN`` features by default."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            features_extractor_class=features_extractor_class,
            **kwargs,
        )


class MultiInputPolicy(SACDiscretePolicy):
    """:class:`SACDiscretePolicy` over Dict observations: SB3's ``CombinedExtractor`` features by default."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            features_extractor_class=features_extractor_class,
            **kwargs,
        )
