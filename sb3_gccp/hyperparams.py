"""rl-zoo style hyperparameter files: read safely, validated, resolved into algorithm arguments.

A file maps environment ids to settings, as in rl-baselines3-zoo::

    GCCPPlanner-v0:
      n_timesteps: 300000
      n_envs: 2
      policy: MotionPlannerPolicy
      learning_rate: {initial: 1.0e-4, final: 1.0e-5, after_gradient_steps: 2000}
      policy_kwargs: {net_arch: {pi: [256, 256], vf: [256, 256]}}
      env_kwargs: {task: mixed}
      n_steps: 512
      ...

Everything that is not one of :data:`RUN_KEYS` goes to the algorithm's constructor. Classes are named
by their alias or dotted import path; nothing is ``eval()``-ed. Unknown keys are errors naming them.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

RUN_KEYS = (
    "n_timesteps",
    "policy",
    "n_envs",
    "env_kwargs",
    "policy_kwargs",
    "normalize",
    "env_wrapper",
    "callback",
    "frame_stack",
)
"""Keys rl-zoo reads itself instead of passing them to the algorithm."""
UNSUPPORTED_RUN_KEYS = ("normalize", "env_wrapper", "callback", "frame_stack")
"""rl-zoo keys our own trainer does not implement (the observation is a dict of masked arrays)."""
POLICY_ALIASES = {
    "MotionPlannerPolicy": "sb3_gccp.policies.MotionPlannerPolicy",
    "DecisionMakerPolicy": "sb3_gccp.policies.DecisionMakerPolicy",
}
"""Short policy names accepted in the ``policy`` key, besides dotted paths and the algorithm's own."""
POLICY_KWARGS_CLASSES = ("features_extractor_class", "activation_fn", "optimizer_class")
"""``policy_kwargs`` keys whose value is a class, named in YAML by its dotted import path."""


class HyperparamsError(ValueError):
    """A hyperparameter file that cannot be used, with a one-line reason."""


@dataclass(frozen=True)
class StepSchedule:
    """A learning rate that drops from ``initial`` to ``final`` once progress passes ``switch``.

    SB3 schedules see the remaining progress (1 at the start, 0 at the end); the paper counts gradient
    steps, converted by :func:`resolve_schedule` for a known budget.
    """

    initial: float
    final: float
    switch_remaining: float

    def __call__(self, progress_remaining: float) -> float:
        """The learning rate at this point of training."""
        return self.initial if progress_remaining > self.switch_remaining else self.final


def read_yaml_mapping(path: str | Path, what: str) -> dict[str, Any]:
    """A YAML file holding a mapping (an empty file is an empty mapping), read with ``safe_load``.

    :param what: how errors name the file, e.g. "hyperparameter file"
    :raises HyperparamsError: missing file, not UTF-8 text, bad YAML, or not a mapping
    """
    file = Path(path)
    if not file.is_file():
        raise HyperparamsError(f"{what} not found: {path}")
    try:
        data = yaml.safe_load(file.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise HyperparamsError(f"{what} {path} is not UTF-8 text (byte {err.start}: {err.reason})") from err
    except yaml.YAMLError as err:
        raise HyperparamsError(f"{what} {path} is not valid YAML: {str(err).splitlines()[0]}") from err
    if data is not None and not isinstance(data, dict):
        raise HyperparamsError(f"{what} {path} must hold a mapping")
    return dict(data or {})


def load_hyperparams(path: str | Path, env_id: str) -> dict[str, Any]:
    """The settings of ``env_id`` in a zoo-style YAML file.

    :raises HyperparamsError: missing file, bad YAML, or no entry for ``env_id``
    """
    data = read_yaml_mapping(path, "hyperparameter file")
    if env_id not in data:
        raise HyperparamsError(
            f"{path} has no entry for {env_id} (entries: {', '.join(map(str, data)) or 'none'})"
        )
    settings = data[env_id]
    if not isinstance(settings, dict):
        raise HyperparamsError(f"{path}: the entry for {env_id} must be a mapping")
    return dict(settings)


def check_keys(settings: Mapping[str, Any], algorithm: type) -> None:
    """Reject keys that are neither run keys nor arguments of the algorithm's constructor."""
    allowed = set(RUN_KEYS) | set(inspect.signature(algorithm).parameters) - {"self", "env"}
    unknown = sorted(set(settings) - allowed)
    if unknown:
        raise HyperparamsError(
            "unknown hyperparameter(s): " + ", ".join(_with_hint(k, allowed) for k in unknown)
        )
    unsupported = sorted(set(settings) & set(UNSUPPORTED_RUN_KEYS))
    if unsupported:
        raise HyperparamsError(f"unsupported by sb3_gccp's trainer: {', '.join(unsupported)}")


def _with_hint(key: str, allowed: set[str]) -> str:
    close = difflib.get_close_matches(key, allowed, 1)
    return f"{key!r} (did you mean {close[0]!r}?)" if close else repr(key)


def resolve_class(name: str, aliases: Mapping[str, type] | None = None) -> type:
    """A class from an alias (the algorithm's or ours) or a dotted import path ``package.module.Class``."""
    if aliases and name in aliases:
        return aliases[name]
    path = POLICY_ALIASES.get(name, name)
    module_name, _, class_name = path.rpartition(".")
    if not module_name:
        known = sorted({*(aliases or {}), *POLICY_ALIASES})
        raise HyperparamsError(f"unknown class name {name!r}: use one of {', '.join(known)} or a dotted path")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as err:
        raise HyperparamsError(f"cannot import {path!r}: {err}") from err
    if not isinstance(cls, type):
        raise HyperparamsError(f"{path!r} is not a class")
    return cls


def resolve_schedule(value: Any, key: str, gradient_steps_per_timestep: float, n_timesteps: int) -> Any:
    """A number, or a step schedule given as ``{initial, final, after_gradient_steps}``.

    :param gradient_steps_per_timestep: optimiser steps the algorithm takes per environment step
    :param n_timesteps: the run's budget, to convert gradient steps into progress
    """
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, dict) and set(value) == {"initial", "final", "after_gradient_steps"}:
        switch_timestep = float(value["after_gradient_steps"]) / gradient_steps_per_timestep
        return StepSchedule(
            float(value["initial"]),
            float(value["final"]),
            1.0 - min(switch_timestep / max(n_timesteps, 1), 1.0),
        )
    raise HyperparamsError(
        f"{key} must be a number or a map with initial, final, after_gradient_steps; " f"got {value!r}"
    )


def ppo_gradient_steps_per_timestep(settings: Mapping[str, Any], defaults: Mapping[str, Any]) -> float:
    """Optimiser steps of (Maskable)PPO per environment step: n_epochs / batch_size.

    :raises HyperparamsError: ``n_epochs`` under 1 or ``batch_size`` under 2 (PPO's own minimum)
    """
    n_epochs = settings.get("n_epochs", defaults["n_epochs"])
    batch_size = settings.get("batch_size", defaults["batch_size"])
    for key, value, minimum in (("n_epochs", n_epochs, 1), ("batch_size", batch_size, 2)):
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise HyperparamsError(f"{key} must be an integer of at least {minimum}, got {value!r}")
    return n_epochs / batch_size


def off_policy_gradient_steps_per_timestep(settings: Mapping[str, Any], defaults: Mapping[str, Any]) -> float:
    """Optimiser steps of an SB3 off-policy algorithm per environment step.

    ``gradient_steps`` follow every ``train_freq`` steps of each of the ``n_envs`` envs; -1 means one per
    collected transition.

    :raises HyperparamsError: ``train_freq`` counted in episodes, which has no fixed rate
    """
    train_freq = settings.get("train_freq", defaults["train_freq"])
    frequency, unit = (train_freq, "step") if isinstance(train_freq, int) else tuple(train_freq)
    if unit != "step":
        raise HyperparamsError(f"a learning-rate step schedule needs train_freq in steps, got {train_freq!r}")
    gradient_steps = int(settings.get("gradient_steps", defaults["gradient_steps"]))
    if gradient_steps < 0:
        return 1.0
    return gradient_steps / (int(frequency) * int(settings.get("n_envs", 1)))


def gradient_steps_per_timestep(algorithm: type, settings: Mapping[str, Any]) -> float:
    """Optimiser steps per environment step of an SB3 off-policy algorithm or of (Maskable)PPO."""
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    defaults = constructor_defaults(algorithm)
    if issubclass(algorithm, OffPolicyAlgorithm):
        return off_policy_gradient_steps_per_timestep(settings, defaults)
    return ppo_gradient_steps_per_timestep(settings, defaults)


def resolve_policy_kwargs(policy_kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """``policy_kwargs`` with the classes of :data:`POLICY_KWARGS_CLASSES` imported from their dotted paths.

    :raises HyperparamsError: a class that cannot be imported
    """
    return {
        key: resolve_class(value) if key in POLICY_KWARGS_CLASSES and isinstance(value, str) else value
        for key, value in policy_kwargs.items()
    }


def constructor_defaults(algorithm: type) -> dict[str, Any]:
    """Default values of an algorithm's constructor arguments."""
    return {
        name: p.default
        for name, p in inspect.signature(algorithm).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def default_config_file(name: str) -> Path:
    """A shipped zoo config: ``zoo_configs/<name>`` of the checkout, or its installed copy in a wheel."""
    source = Path(__file__).resolve().parents[1] / "zoo_configs" / name
    if source.is_file():
        return source
    import importlib.resources

    try:
        installed = importlib.resources.files("sb3_gccp.zoo_configs") / name
    except ModuleNotFoundError:
        return source
    return Path(str(installed))
