"""What one trial of ``sb3_gccp tune`` does: train a method with the trial's hyperparameters for a fixed
episode budget, report the rolling success rate to Optuna as it goes, and return it at the end.

The methods are the baselines on ``GCCPFlat-v0`` (``dqn``, ``ppo``, ``sac_discrete``, trained by
:func:`~sb3_gccp.training.baselines.train_baseline`) and the decision-maker on ``GCCPDecider-v0``
(``decider``, trained by :func:`~sb3_gccp.training.decider.train_decider` over a frozen planner).
"""

from __future__ import annotations

import copy
import difflib
import inspect
import math
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import yaml
from sb3_contrib import MaskablePPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

from gccp_envs.config import IntersectionConfig, reject_unknown_keys
from sb3_gccp.constants import DECIDER_ENV_ID, EPISODES_FILE, FLAT_ENV_ID
from sb3_gccp.gccp.settings import CHECK_KEYS, GCCPSettings
from sb3_gccp.hyperparams import (
    RUN_KEYS,
    HyperparamsError,
    check_keys,
    constructor_defaults,
    default_config_file,
    load_hyperparams,
    resolve_class,
    resolve_policy_kwargs,
)
from sb3_gccp.training.baselines import BASELINES, MASKS_KEY, baseline_algorithm, max_episode_steps
from sb3_gccp.training.episodes import read_episodes, rolling_rate
from sb3_gccp.tune.space import SearchSpace, SearchSpaceError

WINDOW = 100
"""Episodes of the rolling success rate a trial is judged by (fewer when the budget is smaller)."""
FIXED_KEYS = ("n_timesteps", "env_kwargs", "policy", "gccp.n_episodes")
"""Zoo keys a study does not sample: the budget (``--episodes-per-trial``), the world and the policy."""


@dataclass(frozen=True)
class TuneMethod:
    """A method ``sb3_gccp tune`` can tune: its env, shipped zoo file and algorithm."""

    name: str
    env_id: str
    zoo_file: str
    """The shipped zoo file whose ``env_id`` entry trials start from."""
    own_keys: tuple[str, ...] = ()
    """Keys of the entry that are sb3_gccp's own rather than the algorithm's (the decider's ``gccp``)."""

    @property
    def algorithm(self) -> type[BaseAlgorithm]:
        """The algorithm class (imported when first used): a baseline's masked one, as the shipped
        entries train (``action_masks: true``; the unmasked classes take the same hyperparameters)."""
        return MaskablePPO if self.name == "decider" else baseline_algorithm(self.name, masked=True)

    def check_key(self, name: str, entry: Mapping[str, Any]) -> None:
        """Reject a dotted zoo key this method does not take, or one a study must not sample.

        :param entry: the entry trials start from (a nested key must go into a map there, or into
            ``policy_kwargs`` / ``gccp``)
        :raises ValueError: one line naming the key
        """
        head, *rest = name.split(".")
        if name in FIXED_KEYS or head in ("n_timesteps", "env_kwargs", "policy"):
            raise ValueError(
                "not a tuned key: the budget is --episodes-per-trial, the world and policy are the entry's"
            )
        algorithm = self.algorithm
        allowed = set(RUN_KEYS) | set(self.own_keys) | set(inspect.signature(algorithm).parameters)
        if head not in allowed - {"self", "env"}:
            close = difflib.get_close_matches(head, allowed, 1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"{algorithm.__name__} takes no hyperparameter {head!r}{hint}")
        if not rest:
            return
        if head == "policy_kwargs":
            policy = resolve_class(str(entry.get("policy", "MultiInputPolicy")), algorithm.policy_aliases)
            parameters = inspect.signature(policy).parameters
            takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
            if rest[0] not in parameters and not takes_any:
                raise ValueError(f"{policy.__name__} takes no policy_kwargs key {rest[0]!r}")
        elif head == "gccp":
            known = [f.name for f in fields(GCCPSettings) if f.name != "check"] + list(CHECK_KEYS)
            reject_unknown_keys({rest[0]: None}, GCCPSettings, "gccp settings", known)
        elif not isinstance(entry.get(head), Mapping):
            raise ValueError(f"{head} is not a map in the entry, so {name!r} has nowhere to go")

    def check_space(self, space: SearchSpace, entry: Mapping[str, Any], episodes: int) -> None:
        """Check before any trial that the entry takes every value the space can give: integers where
        the algorithm's argument defaults to one, and the whole entry at both ends of every range.

        :raises SearchSpaceError: one line naming the file and the key
        """
        defaults = constructor_defaults(self.algorithm)
        for parameter in space.hyperparams:
            default = defaults.get(parameter.name)
            if parameter.type == "float" and isinstance(default, int) and not isinstance(default, bool):
                raise SearchSpaceError(
                    f"search space {space.source}: {parameter.name}: {self.algorithm.__name__} takes an "
                    f"integer (default {default}), the space samples floats: use type int"
                )
        for end in (0, 1):
            values = {p.name: p.bounds()[end] for p in space.hyperparams}
            try:
                self.check_entry(trial_entry(self, entry, values, episodes))
            except (ValueError, TypeError) as err:
                raise SearchSpaceError(f"search space {space.source}: {err}") from err

    def check_entry(self, entry: dict[str, Any]) -> None:
        """Reject an entry its trainer would reject (keys, ``gccp`` map, world, policy classes)."""
        check_keys({k: v for k, v in entry.items() if k not in self.own_keys}, self.algorithm)
        if "gccp" in self.own_keys:
            GCCPSettings.from_dict(entry.get("gccp"))
        IntersectionConfig.from_dict(entry.get("env_kwargs") or {})
        resolve_policy_kwargs(entry.get("policy_kwargs") or {})

    def base_entry(self, config_file: Path | None) -> dict[str, Any]:
        """The entry trials start from: ``config_file``'s (default: the shipped zoo file's)."""
        return load_hyperparams(config_file or default_config_file(self.zoo_file), self.env_id)


TUNE_METHODS = {
    **{name: TuneMethod(name, FLAT_ENV_ID, f"{name}.yml", own_keys=(MASKS_KEY,)) for name in BASELINES},
    "decider": TuneMethod("decider", DECIDER_ENV_ID, "ppo_mask.yml", own_keys=("gccp",)),
}
"""The methods ``sb3_gccp tune --method`` takes."""


def with_values(entry: Mapping[str, Any], values: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of a zoo entry with dotted keys set (``policy_kwargs.net_arch``), maps made as needed."""
    result = copy.deepcopy(dict(entry))
    for name, value in values.items():
        *path, last = name.split(".")
        target = result
        for part in path:
            if not isinstance(target.get(part), dict):
                target[part] = {}
            target = target[part]
        target[last] = copy.deepcopy(value)
    return result


def trial_entry(
    method: TuneMethod, entry: Mapping[str, Any], values: Mapping[str, Any], episodes: int
) -> dict[str, Any]:
    """The zoo entry a trial trains: ``entry`` with the trial's values and the episode budget (a
    baseline's ``n_timesteps`` is that many full-length episodes, as in ``reproduce``, so that
    schedules over the run see the same run length whatever the hyperparameters)."""
    result = with_values(entry, values)
    if method.name == "decider":
        result["gccp"] = {**(result.get("gccp") or {}), "n_episodes": episodes}
    else:
        world = IntersectionConfig.from_dict(result.get("env_kwargs") or {})
        result["n_timesteps"] = episodes * max_episode_steps(world)
    return result


class SuccessReporter(BaseCallback):
    """Reports the rolling success rate to an Optuna trial every ``every`` episodes, and stops training
    when the trial's pruner says so.

    :param trial: the Optuna trial
    :param every: episodes between reports
    :param window: episodes of the rolling success rate
    """

    def __init__(self, trial: optuna.Trial, every: int, window: int = WINDOW) -> None:
        super().__init__()
        self.trial = trial
        self.every = every
        self.window = window
        self.successes: list[bool] = []
        self.pruned = False

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
            if not done:
                continue
            self.successes.append(bool(info.get("is_success")))
            if len(self.successes) % self.every == 0:
                self.trial.report(float(np.mean(self.successes[-self.window :])), len(self.successes))
                if self.trial.should_prune():
                    self.pruned = True
                    return False
        return True


@dataclass(frozen=True)
class TrialSettings:
    """What every trial of a study shares (plain data: worker processes receive it)."""

    method: TuneMethod
    space: SearchSpace
    entry: dict[str, Any]
    """The entry trials start from."""
    episodes: int
    """The episode budget of every trial."""
    study_dir: Path
    """Trial run folders go here: ``trial_<number>``."""
    seed: int = 0
    """Seed of every trial's training (the trials differ only in their hyperparameters)."""
    torch_threads: int = 1
    planner: Path | None = None
    """The frozen motion-planner of the decider's trials."""
    argv: list[str] = field(default_factory=list)


def run_trial(trial: optuna.Trial, settings: TrialSettings) -> float:
    """Train the trial's hyperparameters in ``trial_<number>/``; return the final rolling success rate.

    :raises optuna.TrialPruned: the pruner stopped it, or its hyperparameters broke training (a
        ``ValueError`` or ``AssertionError`` such as NaN logits, as rl-zoo3 treats them)
    """
    values = settings.space.sample(trial)
    entry = trial_entry(settings.method, settings.entry, values, settings.episodes)
    run_dir = settings.study_dir / f"trial_{trial.number:04d}"
    trial.set_user_attr("run_dir", str(run_dir.resolve()))
    reporter = SuccessReporter(trial, settings.space.pruner.report_every)
    with tempfile.TemporaryDirectory() as folder:
        config_file = Path(folder) / "entry.yml"
        config_file.write_text(yaml.safe_dump({settings.method.env_id: entry}, sort_keys=False))
        try:
            _train(settings, config_file, run_dir, reporter)
        except HyperparamsError:
            raise
        except (ValueError, AssertionError) as err:
            trial.set_user_attr("error", str(err).splitlines()[0] if str(err) else type(err).__name__)
            raise optuna.TrialPruned(f"training failed: {err}") from err
    if reporter.pruned:
        raise optuna.TrialPruned(f"pruned after {len(reporter.successes)} episodes")
    return final_success(run_dir)


def _train(settings: TrialSettings, config_file: Path, run_dir: Path, reporter: SuccessReporter) -> None:
    if settings.method.name == "decider":
        from sb3_gccp.training.decider import train_decider
        from sb3_gccp.training.run_folder import StageRequest

        request = StageRequest(
            config_file=config_file,
            seed=settings.seed,
            run_dir=run_dir,
            progress_bar=False,
            torch_threads=settings.torch_threads,
            planner=settings.planner,
            argv=settings.argv,
        )
        train_decider(request, callback=reporter)
    else:
        from sb3_gccp.training.baselines import train_baseline

        train_baseline(
            settings.method.name, config_file, run_dir, settings.seed, settings.episodes, callback=reporter
        )


def final_success(run_dir: Path, window: int = WINDOW) -> float:
    """The success rate over the last ``window`` training episodes of a run folder (fewer if it has fewer)."""
    rates = rolling_rate([row["success"] for row in read_episodes(run_dir / EPISODES_FILE)], window)
    return float(rates[-1]) if len(rates) else math.nan
