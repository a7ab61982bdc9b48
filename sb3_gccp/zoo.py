"""rl-baselines3-zoo's own trainer for our algorithms and environments.

Usage (every rl-zoo option works, e.g. ``-n``, ``--seed``, ``-f``, ``--eval-freq``)::

    python -m sb3_gccp.zoo --algo ppo_mask --env GCCPPlanner-v0 --conf-file zoo_configs/ppo_mask.yml
    python -m sb3_gccp.zoo --algo sac_discrete --env CartPole-v1 --conf-file zoo_configs/sac_discrete.yml

rl-zoo3 2.9.2 knows neither ``ppo_mask`` nor ``sac_discrete`` and evaluates without action masks; this
launcher registers MaskablePPO (with our policy names) and :class:`~sb3_gccp.sac_discrete.SACDiscrete`,
evaluates MaskablePPO with sb3-contrib's masked evaluation, teaches rl-zoo our
``{initial, final, after_gradient_steps}`` learning-rate schedule and imports the classes that
``policy_kwargs`` names by dotted path (rl-zoo would ``eval()`` a string instead), then hands over to
``rl_zoo3.train``. The command line is passed through untouched.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.callbacks import MaskableEvalCallback
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy

import sb3_gccp  # noqa: F401  (registers the environments)
from sb3_gccp.hyperparams import (
    POLICY_ALIASES,
    HyperparamsError,
    gradient_steps_per_timestep,
    resolve_class,
    resolve_policy_kwargs,
    resolve_schedule,
)
from sb3_gccp.sac_discrete import SACDiscrete

if TYPE_CHECKING:
    from rl_zoo3.exp_manager import ExperimentManager


def _our_policies() -> dict[str, type[BasePolicy]]:
    return {name: resolve_class(name) for name in POLICY_ALIASES}


class ZooMaskablePPO(MaskablePPO):
    """MaskablePPO that also accepts our policy names (rl-zoo passes ``policy`` as a string)."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {**MaskablePPO.policy_aliases}


class ZooEvalCallback(MaskableEvalCallback):
    """rl-zoo's evaluation: with action masks for MaskablePPO, without for the other algorithms."""

    def _init_callback(self) -> None:
        super()._init_callback()
        self.use_masking = isinstance(self.model, MaskablePPO)


def preprocess_hyperparams(
    manager: ExperimentManager, hyperparams: dict[str, Any]
) -> tuple[dict[str, Any], Callable | None, list[BaseCallback], Callable | None]:
    """rl-zoo's hyperparameter preprocessing, after resolving what it cannot read from native YAML.

    Our step schedules are placed for the algorithm's gradient steps per environment step and the
    file's ``n_timesteps`` (rl-zoo applies ``-n`` only afterwards); classes in ``policy_kwargs`` are
    imported from their dotted paths.
    """
    from rl_zoo3.utils import ALGOS

    hyperparams = dict(hyperparams)
    if "imitation" in hyperparams:
        raise HyperparamsError(
            "imitation: cloning the scripted planner runs in `sb3_gccp train --stage planner` only"
        )
    if hyperparams.pop("action_masks", False) and manager.algo != "ppo_mask":
        raise HyperparamsError(
            f"action_masks: a masked {manager.algo} trains with `sb3_gccp reproduce` only; "
            "here use --algo ppo_mask or set action_masks: false"
        )
    schedules = [key for key in ("learning_rate", "clip_range") if isinstance(hyperparams.get(key), dict)]
    if schedules:
        per_timestep = gradient_steps_per_timestep(ALGOS[manager.algo], hyperparams)
        for key in schedules:
            hyperparams[key] = resolve_schedule(
                hyperparams[key], key, per_timestep, int(hyperparams.get("n_timesteps", 1))
            )
    if isinstance(hyperparams.get("policy_kwargs"), dict):
        hyperparams["policy_kwargs"] = resolve_policy_kwargs(hyperparams["policy_kwargs"])
    return _ORIGINAL_PREPROCESS_HYPERPARAMS(manager, hyperparams)


def preprocess_schedules(hyperparams: dict[str, Any]) -> dict[str, Any]:
    """rl-zoo's schedule preprocessing of the values that :func:`preprocess_hyperparams` left as numbers."""
    rest = {k: v for k, v in hyperparams.items() if not callable(v)}
    return {**hyperparams, **_ORIGINAL_PREPROCESS(rest)}


_ORIGINAL_PREPROCESS: Any = None
_ORIGINAL_PREPROCESS_HYPERPARAMS: Any = None


def install() -> None:
    """Register ``ppo_mask``, ``sac_discrete`` and our preprocessing in rl-zoo3 (idempotent)."""
    global _ORIGINAL_PREPROCESS, _ORIGINAL_PREPROCESS_HYPERPARAMS
    from rl_zoo3 import exp_manager
    from rl_zoo3.utils import ALGOS

    ZooMaskablePPO.policy_aliases.update(_our_policies())
    ALGOS["ppo_mask"] = ZooMaskablePPO
    ALGOS["sac_discrete"] = SACDiscrete
    exp_manager.EvalCallback = ZooEvalCallback  # type: ignore[misc]
    manager = exp_manager.ExperimentManager
    if _ORIGINAL_PREPROCESS is None:
        _ORIGINAL_PREPROCESS = manager._preprocess_schedules
        _ORIGINAL_PREPROCESS_HYPERPARAMS = manager._preprocess_hyperparams
        manager._preprocess_schedules = staticmethod(preprocess_schedules)  # type: ignore[method-assign]
        manager._preprocess_hyperparams = preprocess_hyperparams  # type: ignore[method-assign, assignment]


def main() -> None:
    """Install our algorithms into rl-zoo3 and run its trainer on this process's command line."""
    install()
    from rl_zoo3.train import train

    try:
        train()
    except HyperparamsError as err:  # our own checks of the zoo file: one line, not a traceback
        print(f"sb3_gccp.zoo: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
