"""A trained MaskablePPO policy as a plain callable, without ``predict()``'s per-call overhead.

``policy.predict()`` copies and checks its input on every call (about 250 us); inside an option env
the motion-planner runs every 0.1 s step, so the frozen planner runs the policy's logits traced with
:func:`torch.jit.trace` under ``torch.inference_mode()`` and picks the most likely allowed action as
sb3-contrib does (about 1.3 ms for the motion-planner on the 2-core AMD machine, against 2.6 ms for its
modules called from Python and 3 ms for ``_predict``). The policies are loaded without unpickling
(:mod:`sb3_gccp.safe_loading`), their spaces checked against the world's before they act. Loading one
leaves torch's thread count alone: the entry point that owns the process sets it (one thread suits these
small networks)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch as th
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy

from gccp_envs.config import IntersectionConfig
from gccp_envs.option_env import decider_spaces
from gccp_envs.planner_env import planner_spaces
from sb3_gccp.safe_loading import PolicyKind, load_policy
from sb3_gccp.traced import ActionLogits, TraceCache, masked_log_probs, most_likely

MOTION_PLANNER = PolicyKind("motion-planner", MaskablePPO)
"""The planner ``.zip`` of a hierarchy: acts on the planner env's spaces."""
DECISION_MAKER = PolicyKind("decision-maker", MaskablePPO)
"""The decider ``.zip`` of a hierarchy: acts on the option env's spaces."""


class FrozenPolicy:
    """A MaskablePPO policy that maps (observation, action mask) to an action.

    The most likely action comes from the policy's logits traced with :func:`torch.jit.trace` (once per
    observation shape), which runs the same operators on the same weights without the Python of the
    modules (about half the time of a motion-planner's forward), then masked and normalised as
    sb3-contrib's ``MaskableCategorical`` does: the action is the one ``policy.predict(obs,
    action_masks=mask, deterministic=True)`` takes, to the bit. Sampled actions run the policy itself.

    :param policy: the trained policy (see :func:`load_planner` and :func:`load_decider`)
    :param deterministic: take the most likely action (default) or sample
    """

    def __init__(self, policy: MaskableActorCriticPolicy, deterministic: bool = True) -> None:
        self.policy = policy
        self.policy.set_training_mode(False)
        self.deterministic = deterministic
        self._logits = TraceCache(ActionLogits(policy))

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The action for one observation (no batch axis)."""
        tensors = {key: th.as_tensor(value)[None] for key, value in obs.items()}
        masks = None if action_mask is None else np.asarray(action_mask, bool)[None]
        with th.inference_mode():
            if not self.deterministic:
                return int(self.policy._predict(tensors, deterministic=False, action_masks=masks).item())
            return int(most_likely(masked_log_probs(self._logits(tensors), masks)).item())


def load_planner(path: str | Path, world: IntersectionConfig, trusted: bool = False) -> FrozenPolicy:
    """The motion-planner of ``path`` for ``world``, its spaces checked against the planner env's.

    :param trusted: load through ``MaskablePPO.load``, which runs code pickled in the file
    :raises ValueError: one line, when the file is no motion-planner for this world
    """
    return FrozenPolicy(_maskable(load_policy(path, MOTION_PLANNER, *planner_spaces(world), trusted=trusted)))


def load_decider(
    path: str | Path, world: IntersectionConfig, deterministic: bool = True, trusted: bool = False
) -> FrozenPolicy:
    """The decision-maker of ``path`` for ``world``, its spaces checked against the option env's.

    :param deterministic: its most likely subgoal, or (False) one sampled
    :param trusted: load through ``MaskablePPO.load``, which runs code pickled in the file
    :raises ValueError: one line, when the file is no decision-maker for this world
    """
    policy = load_policy(path, DECISION_MAKER, *decider_spaces(world), trusted=trusted)
    return FrozenPolicy(_maskable(policy), deterministic)


@functools.lru_cache(maxsize=8)
def load_frozen_planner(path: str, world: IntersectionConfig) -> FrozenPolicy:
    """:func:`load_planner` once per process, path and world (the option env's planner in a vec-env
    worker)."""
    return load_planner(path, world)


def _maskable(policy: object) -> MaskableActorCriticPolicy:
    """The policy, which the kind's base class guarantees is a maskable one."""
    assert isinstance(policy, MaskableActorCriticPolicy)
    return policy
