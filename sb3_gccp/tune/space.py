"""Search spaces of ``sb3_gccp tune``: which zoo keys a study samples, and how it prunes.

One YAML file per method (``zoo_configs/tune/<method>.yml``), read with ``safe_load``::

    hyperparams:                      # zoo keys of the method's entry; dotted for nested maps
      learning_rate: {type: float, low: 1.0e-5, high: 1.0e-3, log: true}
      n_epochs: {type: int, low: 3, high: 10}
      batch_size: {type: categorical, choices: [64, 128, 256]}
      policy_kwargs.net_arch:         # a map of choices: Optuna stores the label, the entry gets the value
        type: categorical
        choices: {small: [64, 64], large: [256, 256]}
    pruner: {type: median, n_startup_trials: 5, n_warmup_episodes: 20, report_every: 10}

Every problem (an unknown key, a bad range, a key the algorithm does not take, a float for an integer
argument) is a :class:`SearchSpaceError` with a one-line message naming the file and the key.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import optuna

from sb3_gccp.hyperparams import HyperparamsError, read_yaml_mapping

PARAMETER_TYPES = ("float", "int", "categorical")
"""The kinds of a hyperparameter: Optuna's ``suggest_float``, ``suggest_int``, ``suggest_categorical``."""
SPACE_KEYS = ("hyperparams", "pruner")
"""The top-level keys of a search-space file."""
PRUNERS = ("median", "none")
"""``pruner.type``: Optuna's MedianPruner, or no pruning."""


class SearchSpaceError(HyperparamsError):
    """A search-space file that cannot be used, with a one-line reason."""


@dataclass(frozen=True)
class Hyperparameter:
    """One sampled zoo key.

    :param name: the key in the method's zoo entry, dotted for a nested map (``policy_kwargs.net_arch``)
    """

    name: str
    type: str
    low: float | None = None
    """Lowest value (float and int)."""
    high: float | None = None
    """Highest value, included (float and int)."""
    log: bool = False
    """Sample on a log scale (float and int; ``low`` must be positive)."""
    step: float | None = None
    """Spacing of the values from ``low`` (float and int; not with ``log``)."""
    labels: tuple[Any, ...] = ()
    """Categorical: what Optuna stores for each choice (the choice itself, or its label in a map)."""
    values: tuple[Any, ...] = ()
    """Categorical: what the zoo entry gets for each label."""

    @classmethod
    def from_dict(cls, name: str, spec: Any) -> Hyperparameter:
        """A hyperparameter from its YAML map, checked.

        :raises ValueError: one line naming what is wrong
        """
        if not isinstance(spec, Mapping):
            raise ValueError(f"must be a map with a type, got {spec!r}")
        known = ("type", "low", "high", "log", "step", "choices")
        unknown = sorted(set(spec) - set(known))
        if unknown:
            raise ValueError(f"unknown key(s) {', '.join(map(repr, unknown))}: expected {', '.join(known)}")
        kind = spec.get("type")
        if kind not in PARAMETER_TYPES:
            raise ValueError(f"type must be one of {', '.join(PARAMETER_TYPES)}, got {kind!r}")
        if kind == "categorical":
            return cls._categorical(name, spec)
        return cls._numeric(name, kind, spec)

    @classmethod
    def _categorical(cls, name: str, spec: Mapping[str, Any]) -> Hyperparameter:
        extra = sorted(set(spec) - {"type", "choices"})
        if extra:
            raise ValueError(f"a categorical takes only choices, not {', '.join(extra)}")
        choices = spec.get("choices")
        if isinstance(choices, Mapping):
            labels, values = tuple(map(str, choices)), tuple(choices.values())
        elif isinstance(choices, list):
            bad = [c for c in choices if c is not None and not isinstance(c, (bool, int, float, str))]
            if bad:
                raise ValueError(
                    f"choices must be numbers, strings or null; label others in a map: {bad[0]!r}"
                )
            labels = values = tuple(choices)
        else:
            raise ValueError(f"choices must be a non-empty list or map, got {choices!r}")
        if not labels or len(set(labels)) != len(labels):
            raise ValueError("choices must be non-empty and distinct")
        return cls(name, "categorical", labels=labels, values=values)

    @classmethod
    def _numeric(cls, name: str, kind: str, spec: Mapping[str, Any]) -> Hyperparameter:
        if "choices" in spec:
            raise ValueError(f"a{'n' if kind == 'int' else ''} {kind} takes low and high, not choices")
        number = int if kind == "int" else (int, float)
        bounds = {key: spec.get(key) for key in ("low", "high")}
        for key, value in (*bounds.items(), ("step", spec.get("step", 1 if kind == "int" else 0.5))):
            if not isinstance(value, number) or isinstance(value, bool) or not math.isfinite(value):
                what = "an integer" if kind == "int" else "a number"
                raise ValueError(f"{key} must be {what}, got {value!r}")
        low, high = bounds["low"], bounds["high"]
        assert low is not None and high is not None  # numbers, checked above
        log, step = spec.get("log", False), spec.get("step")
        if not isinstance(log, bool):
            raise ValueError(f"log must be true or false, got {log!r}")
        if not low < high:
            raise ValueError(f"low must be below high, got low {low!r}, high {high!r}")
        if log and low <= 0:
            raise ValueError(f"a log scale needs low above 0, got {low!r}")
        if step is not None and (log or step <= 0):
            raise ValueError("step must be positive, and cannot go with log")
        return cls(name, kind, low=low, high=high, log=log, step=step)

    def suggest(self, trial: optuna.Trial) -> Any:
        """The trial's value for the zoo entry (sampled, or given by an enqueued or retried trial)."""
        if self.type == "categorical":
            label = trial.suggest_categorical(self.name, list(self.labels))
            return self.value_of(label)
        assert self.low is not None and self.high is not None
        if self.type == "int":
            step = 1 if self.step is None else int(self.step)
            return trial.suggest_int(self.name, int(self.low), int(self.high), step=step, log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, step=self.step, log=self.log)

    def value_of(self, stored: Any) -> Any:
        """The zoo entry's value for what Optuna stored (a categorical's label)."""
        return self.values[self.labels.index(stored)] if self.type == "categorical" else stored

    def bounds(self) -> tuple[Any, Any]:
        """The two extremes of the range (categorical: its first and last value), for checks."""
        if self.type == "categorical":
            return self.values[0], self.values[-1]
        return self.low, self.high


@dataclass(frozen=True)
class PrunerSettings:
    """How trials are stopped early: the rolling success rate is reported to Optuna every
    ``report_every`` episodes, and a trial below the median of the others at the same episode stops."""

    type: str = "median"
    """``median`` (Optuna's MedianPruner) or ``none``."""
    n_startup_trials: int = 5
    """Trials that finish before any is pruned (MedianPruner's)."""
    n_warmup_episodes: int | None = None
    """Episodes of a trial before it can be pruned; None: a third of the episode budget (rl-zoo3's)."""
    report_every: int = 10
    """Episodes between two reports of the rolling success rate."""

    def __post_init__(self) -> None:
        if self.type not in PRUNERS:
            raise ValueError(f"pruner.type must be one of {', '.join(PRUNERS)}, got {self.type!r}")
        for name in ("n_startup_trials", "n_warmup_episodes", "report_every"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 0):
                raise ValueError(f"pruner.{name} must be a non-negative integer, got {value!r}")
        if self.report_every < 1:
            raise ValueError("pruner.report_every must be at least 1")

    @classmethod
    def from_dict(cls, values: Any) -> PrunerSettings:
        """The ``pruner`` map (None: the defaults), unknown keys rejected."""
        if values is None:
            return cls()
        if not isinstance(values, Mapping):
            raise ValueError(f"pruner must be a map, got {values!r}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(
                f"unknown pruner key(s) {', '.join(map(repr, unknown))}: expected {', '.join(known)}"
            )
        return cls(**values)

    def make(self, episodes: int) -> optuna.pruners.BasePruner:
        """The Optuna pruner for trials of ``episodes`` episodes (steps are episodes)."""
        if self.type == "none":
            return optuna.pruners.NopPruner()
        warmup = episodes // 3 if self.n_warmup_episodes is None else self.n_warmup_episodes
        return optuna.pruners.MedianPruner(
            n_startup_trials=self.n_startup_trials, n_warmup_steps=warmup, interval_steps=1
        )


@dataclass(frozen=True)
class SearchSpace:
    """The hyperparameters a study samples and its pruner, read from a search-space file."""

    hyperparams: tuple[Hyperparameter, ...]
    pruner: PrunerSettings = field(default_factory=PrunerSettings)
    source: str = ""
    """The file it was read from."""

    @classmethod
    def from_file(cls, path: Path, check_key: Callable[[str], None]) -> SearchSpace:
        """Read and check a search-space file.

        :param check_key: raises ``ValueError`` for a dotted zoo key the method does not take
        :raises SearchSpaceError: one line naming the file and the key
        """
        data = read_yaml_mapping(path, "search space")
        unknown = sorted(set(data) - set(SPACE_KEYS))
        if unknown:
            raise SearchSpaceError(
                f"search space {path}: unknown key(s) {', '.join(map(repr, unknown))}: "
                f"expected {', '.join(SPACE_KEYS)}"
            )
        specs = data.get("hyperparams")
        if not isinstance(specs, Mapping) or not specs:
            raise SearchSpaceError(f"search space {path}: hyperparams must be a non-empty map of zoo keys")
        hyperparams = []
        for name, spec in specs.items():
            try:
                check_key(str(name))
                hyperparams.append(Hyperparameter.from_dict(str(name), spec))
            except (ValueError, TypeError) as err:
                raise SearchSpaceError(f"search space {path}: {name}: {err}") from err
        try:
            pruner = PrunerSettings.from_dict(data.get("pruner"))
        except (ValueError, TypeError) as err:
            raise SearchSpaceError(f"search space {path}: {err}") from err
        return cls(tuple(hyperparams), pruner, str(path))

    def sample(self, trial: optuna.Trial) -> dict[str, Any]:
        """The trial's zoo values, by dotted key."""
        return {p.name: p.suggest(trial) for p in self.hyperparams}

    def values_of(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """The zoo values, by dotted key, of a finished trial's stored ``params``."""
        return {p.name: p.value_of(params[p.name]) for p in self.hyperparams}

    def to_dict(self) -> dict[str, Any]:
        """Plain data that tells two spaces apart (a study keeps its own)."""
        return {
            "hyperparams": {
                p.name: {k: v for k, v in p.__dict__.items() if k != "name" and v not in (None, (), False)}
                for p in self.hyperparams
            },
            "pruner": self.pruner.__dict__,
        }
