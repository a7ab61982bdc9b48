"""A trained MaskablePPO policy as a plain callable, without ``predict()``'s per-call overhead.

``policy.predict()`` copies and checks its input on every call (about 250 us); inside an option env
the motion-planner runs every 0.1 s step, so the frozen planner calls the policy's forward directly
under ``torch.inference_mode()`` (about 40 us for a small network). Loading one leaves torch's thread
count alone: the entry point that owns the process sets it (one thread suits these small networks).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch as th
from sb3_contrib import MaskablePPO


class FrozenPolicy:
    """Loads a MaskablePPO ``.zip`` once and maps (observation, action mask) to an action.

    :param path: the saved model
    :param deterministic: take the most likely action (default) or sample
    """

    def __init__(self, path: str | Path, deterministic: bool = True) -> None:
        self.model = MaskablePPO.load(path, device="cpu")
        self.policy = self.model.policy
        self.policy.set_training_mode(False)
        self.deterministic = deterministic

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The action for one observation (no batch axis)."""
        tensors = {key: th.as_tensor(value)[None] for key, value in obs.items()}
        masks = None if action_mask is None else np.asarray(action_mask, bool)[None]
        with th.inference_mode():
            action = self.policy._predict(tensors, deterministic=self.deterministic, action_masks=masks)
        return int(action.item())


@functools.lru_cache(maxsize=8)
def load_frozen_policy(path: str, deterministic: bool = True) -> FrozenPolicy:
    """A :class:`FrozenPolicy` loaded once per process and path (the option env's planner in a vec-env
    worker)."""
    return FrozenPolicy(path, deterministic=deterministic)
