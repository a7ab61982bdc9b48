"""SB3 policies of the hierarchy: the motion-planner (paper III-D, "Neural Network for Motion-planner").

The motion-planner's policy and value function read the shared scene encoder's ego feature (5L: the
ego's history, interaction, route attention, drivable-area and subgoal features); each head is a
3-layer MLP (two hidden layers of ``net_arch`` plus SB3's output layer) to the N_a = 6 action logits
or to the value. The classes live at stable import paths because saved ``.zip`` files name them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch as th
from gymnasium import spaces
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_gccp.networks import EncoderConfig, SceneEncoder

PLANNER_NET_ARCH = {"pi": [256, 256], "vf": [256, 256]}
"""Hidden layers of the planner's policy and value heads; with the output layer, 3-layer MLPs (paper)."""


class PlannerFeaturesExtractor(BaseFeaturesExtractor):
    """The ego's 5L scene feature conditioned on the observation's ``goal`` (the subgoal).

    :param observation_space: the planner or flat env's Dict space (state arrays and ``goal``)
    :param encoder: :class:`~sb3_gccp.networks.EncoderConfig` fields; missing ones keep their defaults
    """

    def __init__(self, observation_space: spaces.Dict, encoder: Mapping[str, Any] | None = None) -> None:
        config = EncoderConfig.from_dict(encoder)
        super().__init__(observation_space, features_dim=5 * config.hidden_size)
        history, routes, bev = (observation_space[key].shape or () for key in ("history", "routes", "bev"))
        if len(bev) != 3:
            raise ValueError(f"bev must be (channels, height, width), got shape {bev}")
        self.encoder = SceneEncoder(
            config,
            history_features=history[-1],
            route_features=routes[-1],
            bev_shape=(bev[0], bev[1], bev[2]),
        )

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
        features_extractor_kwargs = dict(features_extractor_kwargs or {})
        if encoder is not None:
            features_extractor_kwargs["encoder"] = {**features_extractor_kwargs.get("encoder", {}), **encoder}
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
