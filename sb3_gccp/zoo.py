"""rl-baselines3-zoo's own trainer for our algorithms and environments.

Usage (every rl-zoo option works, e.g. ``-n``, ``--seed``, ``-f``, ``--eval-freq``)::

    python -m sb3_gccp.zoo --algo ppo_mask --env GCCPPlanner-v0 --conf-file zoo_configs/ppo_mask.yml

rl-zoo3 2.9.2 knows no ``ppo_mask`` and evaluates without action masks; this launcher registers
MaskablePPO (with our policy names), swaps in sb3-contrib's masked evaluation callback and teaches
rl-zoo our ``{initial, final, after_gradient_steps}`` learning-rate schedule, then hands over to
``rl_zoo3.train``. The command line is passed through untouched.
"""

from __future__ import annotations

from typing import Any, ClassVar

from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.callbacks import MaskableEvalCallback
from stable_baselines3.common.policies import BasePolicy

import sb3_gccp  # noqa: F401  (registers the environments)
from sb3_gccp.hyperparams import (
    POLICY_ALIASES,
    constructor_defaults,
    ppo_gradient_steps_per_timestep,
    resolve_class,
    resolve_schedule,
)


def _our_policies() -> dict[str, type[BasePolicy]]:
    return {name: resolve_class(name) for name in POLICY_ALIASES}


class ZooMaskablePPO(MaskablePPO):
    """MaskablePPO that also accepts our policy names (rl-zoo passes ``policy`` as a string)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**MaskablePPO.policy_aliases}


def preprocess_schedules(hyperparams: dict[str, Any]) -> dict[str, Any]:
    """rl-zoo's schedule preprocessing, plus our step schedule.

    The step is placed for the file's ``n_timesteps``; rl-zoo applies ``-n`` only afterwards.
    """

    per_timestep = ppo_gradient_steps_per_timestep(hyperparams, constructor_defaults(MaskablePPO))
    for key in ("learning_rate", "clip_range"):
        if isinstance(hyperparams.get(key), dict):
            hyperparams[key] = resolve_schedule(
                hyperparams[key], key, per_timestep, int(hyperparams.get("n_timesteps", 1))
            )
    rest = {k: v for k, v in hyperparams.items() if not callable(v)}
    return {**hyperparams, **_ORIGINAL_PREPROCESS(rest)}


_ORIGINAL_PREPROCESS: Any = None


def install() -> None:
    """Register ``ppo_mask`` and the masked evaluation in rl-zoo3 (idempotent)."""
    global _ORIGINAL_PREPROCESS
    from rl_zoo3 import exp_manager
    from rl_zoo3.utils import ALGOS

    ZooMaskablePPO.policy_aliases.update(_our_policies())
    ALGOS["ppo_mask"] = ZooMaskablePPO
    exp_manager.EvalCallback = MaskableEvalCallback  # type: ignore[misc]
    if _ORIGINAL_PREPROCESS is None:
        _ORIGINAL_PREPROCESS = exp_manager.ExperimentManager._preprocess_schedules
        exp_manager.ExperimentManager._preprocess_schedules = staticmethod(preprocess_schedules)  # type: ignore[method-assign]


def main() -> None:
    """Install our algorithms into rl-zoo3 and run its trainer on this process's command line."""
    install()
    from rl_zoo3.train import train

    train()


if __name__ == "__main__":
    main()
