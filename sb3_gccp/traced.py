"""A policy's forward traced with :func:`torch.jit.trace`, and sb3-contrib's masked categorical
distribution in a few tensor operations.

A motion-planner's forward is about a hundred small operators at batch 1 or 2, where the Python of the
modules costs as much as the arithmetic. A trace runs the same operators on the same weights (shared, so
training in place is seen) without it: about half the time, the same numbers to the bit. The encoder's
branches depend on the observation's shape only, so one trace serves every observation of a shape.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np
import torch as th
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from stable_baselines3.common.policies import BaseModel

Obs = dict[str, th.Tensor]
ShapeKey = tuple[tuple[str, tuple[int, ...]], ...]
Out = TypeVar("Out")

TRACE_AFTER_CALLS = 500
"""Calls of an observation shape before :class:`TraceCache` traces it. Measured on the shipped policies
(2026-12-02, the 2-core AMD machine): a trace takes 0.4-0.5 s and saves 1.1-1.3 ms a call of the
motion-planner and 0.7-0.9 ms of the decision-maker, so it pays for itself after 300-700 calls."""
MASKED_LOGIT = -1e8
"""What sb3-contrib's ``MaskableCategorical`` puts in place of a masked action's logit."""


class TraceCache(Generic[Out]):
    """``module``'s forward traced once per observation shape, after that shape's first
    ``after_calls`` calls (the module itself until then, and where torch cannot trace it: torch 2.13
    calls tracing deprecated, for ``torch.compile``, which needs a compiler at run time). Not pickled: a
    copy traces its own.

    :param after_calls: calls of a shape that run the module before the shape is traced (default
        :data:`TRACE_AFTER_CALLS`): a policy that lives for a few episodes never pays for a trace; a run
        calls each shape tens of thousands of times.
    """

    def __init__(self, module: Callable[[Obs], Out], after_calls: int | None = None) -> None:
        self.module = module
        self.after_calls = TRACE_AFTER_CALLS if after_calls is None else after_calls
        self._traced: dict[ShapeKey, Callable[[Obs], Out]] = {}
        self._calls: dict[ShapeKey, int] = {}

    def __getstate__(self) -> dict[str, object]:
        return {"module": self.module, "after_calls": self.after_calls, "_traced": {}, "_calls": {}}

    def __call__(self, obs: Obs) -> Out:
        key = tuple((name, tuple(value.shape)) for name, value in obs.items())
        traced = self._traced.get(key)
        if traced is not None:
            return traced(obs)
        calls = self._calls.get(key, 0)
        if calls < self.after_calls:
            self._calls[key] = calls + 1
            return self.module(obs)
        with warnings.catch_warnings(), th.no_grad():
            # The branches it warns of depend on the shapes only, which the trace is made for.
            warnings.simplefilter("ignore", th.jit.TracerWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            try:
                traced = th.jit.trace(self.module, (obs,), check_trace=False)
            except (AttributeError, RuntimeError):
                traced = self.module
        self._traced[key] = traced
        return traced(obs)


class ActionLogits(th.nn.Module):
    """A policy's action logits: the part of ``MaskableActorCriticPolicy.get_distribution`` with
    weights."""

    def __init__(self, policy: MaskableActorCriticPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: Obs) -> th.Tensor:
        policy = self.policy
        features = BaseModel.extract_features(policy, obs, policy.pi_features_extractor)
        return policy.action_net(policy.mlp_extractor.forward_actor(features))


class LogitsAndValues(th.nn.Module):
    """A policy's action logits and values from shared features: the part of
    ``MaskableActorCriticPolicy.forward`` with weights."""

    def __init__(self, policy: MaskableActorCriticPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: Obs) -> tuple[th.Tensor, th.Tensor]:
        policy = self.policy
        latent_pi, latent_vf = policy.mlp_extractor(policy.extract_features(obs))
        return policy.action_net(latent_pi), policy.value_net(latent_vf)


def masked_log_probs(logits: th.Tensor, action_masks: np.ndarray | th.Tensor | None) -> th.Tensor:
    """The log-probabilities (B, n) of sb3-contrib's ``MaskableCategorical`` over ``logits`` (B, n)
    with ``action_masks``: normalised, masked actions set to :data:`MASKED_LOGIT` and normalised again
    (twice without masks, as its constructor does)."""
    logits = logits - logits.logsumexp(-1, keepdim=True)
    if action_masks is not None:
        masks = th.as_tensor(action_masks, dtype=th.bool).reshape(logits.shape)
        logits = th.where(masks, logits, th.tensor(MASKED_LOGIT, dtype=logits.dtype))
    return logits - logits.logsumexp(-1, keepdim=True)


def most_likely(log_probs: th.Tensor) -> th.Tensor:
    """The distribution's mode (B,), as sb3-contrib takes it: the most probable action, the first of
    equals."""
    return th.softmax(log_probs, -1).argmax(1)


def sampled(log_probs: th.Tensor) -> th.Tensor:
    """Actions (B,) drawn as torch's ``Categorical.sample`` draws them (the same random numbers)."""
    return th.multinomial(th.softmax(log_probs, -1), 1, True).T.reshape(-1)
