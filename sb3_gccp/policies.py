"""SB3 policies of the hierarchy (paper III-D, "Neural Network for Decision-maker / Motion-planner").

The motion-planner's policy and value function read the shared scene encoder's ego feature (5L: the
ego's history, interaction, route attention, drivable-area and subgoal features); each head is a
3-layer MLP (two hidden layers of ``net_arch`` plus SB3's output layer) to the N_a = 6 action logits
or to the value.

The decision-maker's state feature is the same ego feature with the task goal in place of the
subgoal; another 2-layer MLP encodes each of the N subgoal candidates. Per subgoal, the state
feature and the subgoal feature are concatenated; a 3-layer MLP gives that subgoal's logit, and a
2-layer MLP gives an L-dim value feature; the N value features are flattened into a 2-layer MLP that
gives the value.

The classes live at stable import paths because saved ``.zip`` files name them.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from gccp_envs.option_env import VERDICT_KEY
from sb3_gccp.networks import EncoderConfig, SceneEncoder
from sb3_gccp.traced import LogitsAndValues, TraceCache, masked_log_probs, most_likely, sampled

PLANNER_NET_ARCH = {"pi": [256, 256], "vf": [256, 256]}
"""Hidden layers of the planner's policy and value heads; with the output layer, 3-layer MLPs (paper)."""
DECIDER_NET_ARCH = {"pi": [256, 256], "vf": [256, 256]}
"""Decision-maker heads: ``pi`` the two hidden layers of the per-subgoal logit MLP; ``vf`` the hidden
layer of the per-subgoal value MLP (to L) and the hidden layer of the value MLP over all subgoals."""


class PlannerFeaturesExtractor(BaseFeaturesExtractor):
    """The ego's 5L scene feature conditioned on the observation's ``goal`` (the subgoal).

    :param observation_space: the planner or flat env's Dict space (state arrays and ``goal``)
    :param encoder: :class:`~sb3_gccp.networks.EncoderConfig` fields; missing ones keep their defaults
    """

    def __init__(self, observation_space: spaces.Dict, encoder: Mapping[str, Any] | None = None) -> None:
        config = EncoderConfig.from_dict(encoder)
        super().__init__(observation_space, features_dim=5 * config.hidden_size)
        self.encoder = _scene_encoder(observation_space, config)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Encode a batch of observations into the ego's feature.

        :param observations: preprocessed observation tensors (B, ...)
        :return: (B, 5L)
        """
        scene = self.encoder.encode(observations)
        return self.encoder.ego_features(scene, self.encoder.goal_features(observations["goal"]))


class MotionPlannerPolicy(MaskableActorCriticPolicy):
    """MaskablePPO policy of the motion-planner: scene encoder, then 3-layer MLP policy and value heads.

    Takes every :class:`~sb3_contrib.common.maskable.policies.MaskableActorCriticPolicy` argument;
    only the defaults differ. Encoder sizes come from ``encoder`` (a map of
    :class:`~sb3_gccp.networks.EncoderConfig` fields, for example from YAML ``policy_kwargs``) or
    from ``features_extractor_kwargs={"encoder": ...}``.

    :param observation_space: the planner or flat env's Dict space
    :param action_space: the ego actions (``Discrete(6)``)
    :param lr_schedule: learning rate schedule
    :param net_arch: hidden layers of the heads (default ``PLANNER_NET_ARCH``)
    :param activation_fn: activation of the heads
    :param features_extractor_class: features extractor (default :class:`PlannerFeaturesExtractor`)
    :param features_extractor_kwargs: its keyword arguments
    :param encoder: encoder config fields, merged into ``features_extractor_kwargs["encoder"]``
    :param kwargs: the remaining ``MaskableActorCriticPolicy`` arguments
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = PlannerFeaturesExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        encoder: Mapping[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        features_extractor_kwargs = _with_encoder(features_extractor_kwargs, encoder)
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch if net_arch is not None else {k: list(v) for k, v in PLANNER_NET_ARCH.items()},
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            **kwargs,
        )
        self._heads = TraceCache(LogitsAndValues(self))

    def forward(
        self, obs: PyTorchObs, deterministic: bool = False, action_masks: np.ndarray | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Actions, values and log-probabilities, as ``MaskableActorCriticPolicy.forward`` gives them to
        the bit (the same random numbers drawn); without gradients (PPO's rollouts), from the network
        traced (:mod:`sb3_gccp.traced`), when the actor and the critic share the features extractor."""
        if th.is_grad_enabled() or not isinstance(obs, dict) or not self.share_features_extractor:
            return super().forward(obs, deterministic, action_masks)  # type: ignore[arg-type]
        logits, values = self._heads(obs)
        log_probs = masked_log_probs(logits.view(-1, logits.shape[-1]), action_masks)
        actions = most_likely(log_probs) if deterministic else sampled(log_probs)
        return actions, values, log_probs.gather(-1, actions[:, None]).squeeze(-1)


class DeciderFeaturesExtractor(BaseFeaturesExtractor):
    """The decision-maker's state feature (ego feature with the task goal) and N subgoal features.

    A subgoal's feature encodes its pose and, when the observation carries it (world key
    ``observe_mask``), the GCCP check's verdict on it.

    Output: ``[state (5L), subgoal_0 (L), ..., subgoal_{N-1} (L)]``, flattened.

    :param observation_space: the decider env's Dict space (state arrays, ``task_goal``, ``subgoals``)
    :param encoder: :class:`~sb3_gccp.networks.EncoderConfig` fields; missing ones keep their defaults
    """

    def __init__(self, observation_space: spaces.Dict, encoder: Mapping[str, Any] | None = None) -> None:
        config = EncoderConfig.from_dict(encoder)
        subgoals = observation_space["subgoals"].shape or ()
        self.num_subgoals = int(subgoals[0])
        hidden = config.hidden_size
        super().__init__(observation_space, features_dim=5 * hidden + self.num_subgoals * hidden)
        self.encoder = _scene_encoder(observation_space, config)
        self.observes_verdict = VERDICT_KEY in observation_space.spaces
        self.subgoal_encoder = nn.Sequential(
            nn.Linear(3 + self.observes_verdict, hidden), nn.ReLU(), nn.Linear(hidden, hidden)
        )
        self.state_size, self.subgoal_size = 5 * hidden, hidden

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Encode a batch of decider observations.

        :param observations: preprocessed observation tensors (B, ...)
        :return: (B, 5L + N L)
        """
        scene = self.encoder.encode(observations)
        state = self.encoder.ego_features(scene, self.encoder.goal_features(observations["task_goal"]))
        subgoals = observations["subgoals"] * self.encoder.goal_scale
        if self.observes_verdict:
            subgoals = th.cat((subgoals, observations[VERDICT_KEY][..., None]), -1)
        return th.cat((state, self.subgoal_encoder(subgoals).flatten(1)), -1)


class SubgoalHeads(nn.Module):
    """Per-subgoal policy and value decoders of the decision-maker (SB3's ``mlp_extractor`` slot).

    ``forward_actor`` gives the last hidden layer of each subgoal's logit MLP, flattened (N x h_pi);
    :class:`SubgoalLogits` (the policy's ``action_net``) maps each to one logit. ``forward_critic``
    gives the hidden layer of the value MLP over all subgoals; SB3's ``value_net`` maps it to the value.

    :param state_size: width of the state feature (5L)
    :param subgoal_size: width of a subgoal feature (L)
    :param num_subgoals: N
    :param net_arch: ``{"pi": [h1, h2], "vf": [h_subgoal, h_value]}``
    :param activation_fn: activation after every hidden layer
    """

    def __init__(
        self,
        state_size: int,
        subgoal_size: int,
        num_subgoals: int,
        net_arch: Mapping[str, list[int]],
        activation_fn: type[nn.Module],
    ) -> None:
        super().__init__()
        pi, vf = list(net_arch["pi"]), list(net_arch["vf"])
        if len(pi) < 1 or len(vf) != 2:
            raise ValueError(
                f"decider net_arch needs pi: [h, ...] and vf: [h_subgoal, h_value], got {net_arch}"
            )
        self.state_size, self.subgoal_size, self.num_subgoals = state_size, subgoal_size, num_subgoals
        self.policy_net = _mlp(state_size + subgoal_size, pi, activation_fn)
        self.subgoal_value_net = _mlp(state_size + subgoal_size, [vf[0], subgoal_size], activation_fn)
        self.value_net = _mlp(num_subgoals * subgoal_size, [vf[1]], activation_fn)
        self.latent_dim_pi = num_subgoals * pi[-1]
        self.latent_dim_vf = vf[1]

    def _pairs(self, features: th.Tensor) -> th.Tensor:
        """(B, N, 5L + L): the state feature next to each subgoal feature."""
        state, subgoals = features.split((self.state_size, self.num_subgoals * self.subgoal_size), -1)
        subgoals = subgoals.view(-1, self.num_subgoals, self.subgoal_size)
        return th.cat((state[:, None].expand(-1, self.num_subgoals, -1), subgoals), -1)

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Both latents, as SB3's ``MlpExtractor``."""
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:
        """(B, N h_pi) per-subgoal policy latents, flattened."""
        return self.policy_net(self._pairs(features)).flatten(1)

    def forward_critic(self, features: th.Tensor) -> th.Tensor:
        """(B, h_value) value latent from all subgoals' value features."""
        return self.value_net(self.subgoal_value_net(self._pairs(features)).flatten(1))


class SubgoalLogits(nn.Module):
    """One logit per subgoal from its policy latent: a linear layer shared by the subgoals.

    :param latent_size: h_pi, the width of one subgoal's latent
    """

    def __init__(self, latent_size: int) -> None:
        super().__init__()
        self.latent_size = latent_size
        self.linear = nn.Linear(latent_size, 1)

    def forward(self, latent: th.Tensor) -> th.Tensor:
        """(B, N h_pi) -> (B, N) logits."""
        return self.linear(latent.view(latent.shape[0], -1, self.latent_size)).squeeze(-1)


class DecisionMakerPolicy(MaskableActorCriticPolicy):
    """MaskablePPO policy of the decision-maker: one logit per subgoal candidate (paper III-D).

    Takes every :class:`~sb3_contrib.common.maskable.policies.MaskableActorCriticPolicy` argument.
    ``net_arch`` is ``{"pi": [h1, h2], "vf": [h_subgoal, h_value]}`` (default ``DECIDER_NET_ARCH``);
    encoder sizes come from ``encoder`` as for :class:`MotionPlannerPolicy`.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = DeciderFeaturesExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        encoder: Mapping[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        features_extractor_kwargs = _with_encoder(features_extractor_kwargs, encoder)
        if isinstance(net_arch, list) or kwargs.get("share_features_extractor") is False:
            raise ValueError(
                "DecisionMakerPolicy needs net_arch {pi: [...], vf: [h_subgoal, h_value]} "
                "and a shared features extractor"
            )
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch if net_arch is not None else {k: list(v) for k, v in DECIDER_NET_ARCH.items()},
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            **kwargs,
        )

    def _build_mlp_extractor(self) -> None:
        extractor = self.features_extractor
        assert isinstance(extractor, DeciderFeaturesExtractor)
        assert isinstance(self.net_arch, dict)
        self.mlp_extractor = SubgoalHeads(  # type: ignore[assignment]
            extractor.state_size,
            extractor.subgoal_size,
            extractor.num_subgoals,
            self.net_arch,
            self.activation_fn,
        ).to(self.device)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        # SB3's action_net maps the whole latent to N logits; ours scores each subgoal alike.
        assert isinstance(self.net_arch, dict)
        self.action_net = SubgoalLogits(self.net_arch["pi"][-1]).to(self.device)
        if self.ortho_init:
            self.action_net.apply(partial(self.init_weights, gain=0.01))
        self.optimizer = self.optimizer_class(
            self.parameters(),
            lr=lr_schedule(1),
            **self.optimizer_kwargs,  # type: ignore[call-arg]
        )


def _mlp(in_size: int, layers: list[int], activation_fn: type[nn.Module]) -> nn.Sequential:
    """Linear layers of the given widths, each followed by the activation."""
    modules: list[nn.Module] = []
    for width in layers:
        modules += [nn.Linear(in_size, width), activation_fn()]
        in_size = width
    return nn.Sequential(*modules)


def _scene_encoder(observation_space: spaces.Dict, config: EncoderConfig) -> SceneEncoder:
    """A scene encoder sized for the state arrays of ``observation_space``."""
    history, routes, bev = (observation_space[key].shape or () for key in ("history", "routes", "bev"))
    if len(bev) != 3:
        raise ValueError(f"bev must be (channels, height, width), got shape {bev}")
    return SceneEncoder(
        config, history_features=history[-1], route_features=routes[-1], bev_shape=(bev[0], bev[1], bev[2])
    )


def _with_encoder(
    features_extractor_kwargs: dict[str, Any] | None, encoder: Mapping[str, Any] | None
) -> dict[str, Any]:
    """``features_extractor_kwargs`` with the policy's ``encoder`` fields merged into its ``encoder``."""
    kwargs = dict(features_extractor_kwargs or {})
    if encoder is not None:
        kwargs["encoder"] = {**kwargs.get("encoder", {}), **encoder}
    return kwargs
