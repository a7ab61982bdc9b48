"""``sb3_gccp reproduce``: the paper's Tables I and II and Figs. 5-8, every method on the same budget.

The methods of Table I (DQN, PPO and SAC-Discrete on the flat env; ours, the full hierarchy) and of
Table II (ours with the constant-velocity predictor, without GCCP, without the goal condition) train
for the same number of episodes N_e per training seed. The four hierarchy variants share one
motion-planner per seed (trained first, or given with ``--planner``); its pre-training is an extra cost
of ours, reported in ``results.json``. Every method is then evaluated on the same seeded traffic
flows per task (seeds ``eval_seed ..``), the flat env and the option env resetting the same world.

Folders::

    <log_folder>/reproduce/<preset>/
        preset.yml                      the preset settings these runs were made with
        seed<k>/planner/                the motion-planner run (none with --planner)
        seed<k>/<method>/               a decider run folder (hierarchy variants, see decider_stage) or
                                        a baseline run folder (see baselines), plus training.json once
                                        training finished and evaluation.json
        seed<k>/predictor_errors.json   Fig. 7's numbers
    <out>/
        configs/<method>.yml            the zoo file each method trained from (and configs/planner.yml)
        table1.md, table2.md            the paper's tables: success / collision per task, timeouts
        results.csv, results.json       one row per method x seed x task; everything behind the tables
        fig5_baselines.png              success rate vs episode, ours vs the baselines
        fig6_ablations.png              success rate vs episode, ours vs the ablations
        fig7_predictor_errors.png       ADE/FDE at 1 s: learned, no-goal and constant-velocity predictor
        fig8_predictions.png            goal-conditioned predictions in three scenes

Running the command again skips every method whose run holds ``training.json`` (and its evaluation,
when ``evaluation.json`` matches); an unfinished planner or hierarchy variant continues from its last
checkpoint, an unfinished baseline starts over.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import difflib
import filecmp
import json
import math
import shutil
import sys
import time
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from sb3_contrib import MaskablePPO
from stable_baselines3.common.monitor import load_results

from gccp_envs.config import DT, TASKS, IntersectionConfig, reject_unknown_keys, require_int
from sb3_gccp.baselines import (
    BASELINE_FILE,
    FLAT_ENV_ID,
    baseline_algorithm,
    has_checkpoint,
    load_baseline,
    max_episode_steps,
    train_baseline,
    write_baseline_spec,
)
from sb3_gccp.callbacks import read_episodes
from sb3_gccp.decider_stage import DECIDER_ENV_ID, gccp_settings, rolling_rate, train_decider
from sb3_gccp.evaluation import evaluate, summarize
from sb3_gccp.hierarchy import SCRIPTED, load_hierarchy
from sb3_gccp.hyperparams import check_keys, default_config_file, load_hyperparams, resolve_policy_kwargs
from sb3_gccp.networks import EncoderConfig
from sb3_gccp.prediction import ConstantVelocityPredictor, load_predictor
from sb3_gccp.predictor_stage import HELDOUT_SEED_OFFSET, plot_scene
from sb3_gccp.predictor_training import displacement_errors
from sb3_gccp.replay import EpisodeReplayBuffer, collect_decisions
from sb3_gccp.stages import PLANNER_ENV_ID, StageRequest, run_budget, train_planner

PLANNER_EXTRACTOR = "sb3_gccp.policies.PlannerFeaturesExtractor"
CURVE_COLORS = {
    "ours": "black",
    "with_cv": "tab:purple",
    "without_gccp": "tab:brown",
    "without_goal": "tab:pink",
    "dqn": "tab:blue",
    "ppo": "tab:orange",
    "sac_discrete": "tab:green",
}
"""One colour per method in Figs. 5 and 6 (ours the same in both)."""
CURVE_WINDOW = 100
"""Episodes of the rolling success rate in Figs. 5 and 6 (fewer at the start)."""


@dataclass(frozen=True)
class Method:
    """A row of the paper's tables."""

    name: str
    """Name on the command line and of the run folder."""
    label: str
    """Name in the tables and figures (the paper's)."""
    predictor: str | None = None
    """``gccp.predictor`` of a hierarchy variant; None for a baseline on the flat env."""

    @property
    def is_hierarchy(self) -> bool:
        """Whether this is a variant of the hierarchy (else a flat baseline)."""
        return self.predictor is not None


METHODS = {
    m.name: m
    for m in (
        Method("ours", "ours", "learned"),
        Method("with_cv", "w/ CV", "cv"),
        Method("without_gccp", "w/o GCCP", "none"),
        Method("without_goal", "w/o goal condition", "no_goal"),
        Method("dqn", "DQN"),
        Method("ppo", "PPO"),
        Method("sac_discrete", "SAC-Discrete"),
    )
}
"""Every method, in training order (ours first)."""
TABLE_1 = ("dqn", "ppo", "sac_discrete", "ours")
TABLE_2 = ("with_cv", "without_gccp", "without_goal", "ours")
PAPER_RESULTS: dict[str, tuple[tuple[float, float], ...]] = {
    "dqn": ((0, 28), (66, 32), (0, 26), (22.0, 28.7)),
    "ppo": ((34, 32), (54, 42), (54, 20), (47.3, 31.3)),
    "sac_discrete": ((64, 4), (74, 18), (84, 8), (74.0, 10.0)),
    "with_cv": ((86, 10), (88, 12), (90, 4), (88.0, 8.7)),
    "without_gccp": ((82, 10), (82, 16), (80, 8), (81.3, 11.3)),
    "without_goal": ((94, 2), (86, 8), (94, 4), (91.3, 4.7)),
    "ours": ((98, 2), (92, 6), (94, 2), (94.7, 3.3)),
}
"""The paper's (success %, collision %) for left, straight, right and overall (SMARTS, 50 flows)."""


@dataclass(frozen=True)
class Preset:
    """The budgets of a reproduction. Every method trains for the same ``episodes``."""

    planner_timesteps: int
    """Motion-planner pre-training steps on GCCPPlanner-v0, an extra cost of ours (paper preset:
    100,000)."""
    episodes: int
    """N_e: training episodes of every method, baselines included (paper: 2000, "same episode budget")."""
    mask_after_episodes: int | None
    """N_m: episodes before the GCCP masks are switched on; None: the decider entry's own
    (``zoo_configs/ppo_mask.yml``: 0, masks from the first episode; the paper: 800)."""
    episodes_per_task: int
    """Evaluation episodes (seeded traffic flows) per task and method (paper: 50)."""
    heldout_episodes: int
    """Episodes ours drives on held-out traffic seeds to collect Fig. 7's decisions."""
    n_envs: int | None = None
    """Env workers of every training run; None keeps each zoo entry's own."""
    encoder: Mapping[str, Any] | None = None
    """EncoderConfig fields of every network (policies and predictors); None: the defaults (L = 128)."""
    world: Mapping[str, Any] = field(default_factory=dict)
    """World config keys of every method, in training and evaluation (see ``sb3_gccp config``)."""
    hyperparams: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """Zoo keys replacing those of an entry (maps merged): under 'planner', 'hierarchy' (the four
    variants) or a baseline's name."""

    def __post_init__(self) -> None:
        for name in ("planner_timesteps", "episodes", "episodes_per_task", "heldout_episodes"):
            require_int(f"preset {name}", getattr(self, name))
        if self.mask_after_episodes is not None:
            require_int("preset mask_after_episodes", self.mask_after_episodes, minimum=0)
        if self.n_envs is not None:
            require_int("preset n_envs", self.n_envs)
        for name in ("encoder", "world", "hyperparams"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, Mapping):
                raise ValueError(f"preset {name} must be a map, got {value!r}")
        groups = ("planner", "hierarchy", *(m.name for m in METHODS.values() if not m.is_hierarchy))
        unknown = sorted(set(self.hyperparams) - set(groups))
        if unknown:
            raise ValueError(
                f"preset hyperparams: unknown group(s) {', '.join(map(repr, unknown))}: "
                f"expected {', '.join(groups)}"
            )
        for group, keys in self.hyperparams.items():
            if not isinstance(keys, Mapping):
                raise ValueError(f"preset hyperparams.{group} must be a map of zoo keys, got {keys!r}")
        IntersectionConfig.from_dict(self.world)
        EncoderConfig.from_dict(self.encoder)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (for YAML and JSON)."""
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> Preset:
        """A preset from a map of its fields, rejecting unknown ones by name."""
        reject_unknown_keys(values, cls, "preset")
        return cls(**values)

    def with_overrides(self, assignments: Mapping[str, Any]) -> Preset:
        """This preset with fields replaced; a dotted key sets one entry of a map field
        (``world.duration``, ``hyperparams.dqn.buffer_size``)."""
        data = self.to_dict()
        for key, value in assignments.items():
            head, *path = key.split(".")
            reject_unknown_keys({head: None}, Preset, "preset")
            if not path:
                data[head] = value
                continue
            target = data
            for part in (head, *path[:-1]):
                if target.get(part) is None:
                    target[part] = {}
                target = target[part]
                if not isinstance(target, dict):
                    raise ValueError(f"preset {key}: {part} is not a map")
            target[path[-1]] = value
        return Preset.from_dict(data)


TRAINING_FIELDS = (
    "planner_timesteps",
    "episodes",
    "mask_after_episodes",
    "n_envs",
    "encoder",
    "world",
    "hyperparams",
)
"""The preset fields a finished run depends on (the others only change its evaluation)."""
QUICK_ENCODER = {
    "hidden_size": 32,
    "num_heads": 2,
    "token_size": 16,
    "token_heads": 2,
    "bev_channels": [8, 8],
}
"""A small scene encoder (L = 32) that keeps the quick preset's updates cheap."""
PRESETS = {
    "quick": Preset(
        planner_timesteps=512,
        episodes=6,
        mask_after_episodes=2,
        episodes_per_task=2,
        heldout_episodes=2,
        n_envs=1,
        encoder=QUICK_ENCODER,
        hyperparams={
            "planner": {"n_steps": 256, "batch_size": 64},
            "hierarchy": {"n_steps": 32, "batch_size": 32},
            "ppo": {"n_steps": 256, "batch_size": 64},
            "dqn": {"learning_starts": 200, "buffer_size": 2000},
            "sac_discrete": {"learning_starts": 200, "buffer_size": 2000},
        },
    ),
    "paper": Preset(
        planner_timesteps=100_000,
        episodes=2000,
        mask_after_episodes=None,
        episodes_per_task=50,
        heldout_episodes=50,
    ),
}
"""``quick`` runs the whole pipeline in minutes; ``paper`` is the paper's budget (hours per seed)."""


# --- the zoo files of the methods ------------------------------------------------------------------
def planner_settings(preset: Preset) -> dict[str, Any]:
    """The planner's zoo entry: ppo_mask.yml's, for ``planner_timesteps`` steps."""
    entry = _shipped_entry("ppo_mask.yml", PLANNER_ENV_ID)
    entry["n_timesteps"] = preset.planner_timesteps
    return _customised(entry, preset, "planner", (("policy_kwargs", "encoder"),))


def method_settings(method: Method, preset: Preset) -> dict[str, Any]:
    """A method's zoo entry: ppo_mask.yml's decider entry with only the ``gccp`` schedule and predictor
    changed, or the baseline's ``GCCPFlat-v0`` entry capped at ``episodes`` full-length episodes."""
    if method.is_hierarchy:
        entry = _shipped_entry("ppo_mask.yml", DECIDER_ENV_ID)
        entry["gccp"] = {
            **(entry.get("gccp") or {}),
            "predictor": method.predictor,
            "n_episodes": preset.episodes,
        }
        if preset.mask_after_episodes is not None:
            entry["gccp"]["mask_after_episodes"] = preset.mask_after_episodes
        return _customised(
            entry,
            preset,
            "hierarchy",
            (("policy_kwargs", "encoder"), ("gccp", "predictor_kwargs", "encoder")),
        )
    entry = _shipped_entry(f"{method.name}.yml", FLAT_ENV_ID)
    encoders: tuple[tuple[str, ...], ...] = ()
    if (entry.get("policy_kwargs") or {}).get("features_extractor_class") == PLANNER_EXTRACTOR:
        encoders = (("policy_kwargs", "features_extractor_kwargs", "encoder"),)
    entry = _customised(entry, preset, method.name, encoders)
    # The episode budget ends training; n_timesteps only caps it (and places step schedules).
    world = IntersectionConfig.from_dict(entry.get("env_kwargs") or {})
    entry["n_timesteps"] = preset.episodes * max_episode_steps(world)
    return entry


def mask_after_episodes(preset: Preset) -> int:
    """N_m of the preset's hierarchy variants: the preset's, or else the decider entry's."""
    return gccp_settings(method_settings(METHODS["ours"], preset)).mask_after_episodes


def _shipped_entry(file: str, env_id: str) -> dict[str, Any]:
    return copy.deepcopy(load_hyperparams(default_config_file(file), env_id))


def _customised(
    entry: dict[str, Any], preset: Preset, group: str, encoder_paths: Sequence[tuple[str, ...]]
) -> dict[str, Any]:
    """The preset's world, workers, encoder and ``hyperparams[group]`` applied to a zoo entry."""
    if preset.world:
        entry["env_kwargs"] = {**(entry.get("env_kwargs") or {}), **preset.world}
    if preset.n_envs is not None:
        entry["n_envs"] = preset.n_envs
    if preset.encoder is not None:
        for path in encoder_paths:
            _merge_into(entry, {path[0]: _nested(path[1:], dict(preset.encoder))})
    _merge_into(entry, copy.deepcopy(dict(preset.hyperparams.get(group) or {})))
    return entry


def _nested(path: Sequence[str], value: Any) -> Any:
    return {path[0]: _nested(path[1:], value)} if path else value


def _merge_into(target: dict[str, Any], update: Mapping[str, Any]) -> None:
    """Merge ``update`` into ``target``: maps key by key, everything else replaced."""
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(target.get(key), dict):
            _merge_into(target[key], value)
        else:
            target[key] = value


def check_settings(method: Method | None, settings: dict[str, Any]) -> None:
    """Reject an entry its trainer would reject, before any training (``method`` None: the planner).

    :raises ValueError: with a one-line reason
    """
    if method is None or method.is_hierarchy:
        own = ("gccp",) if method is not None else ()
        run_budget(settings, own_keys=own)
        if method is not None:
            gccp_settings(settings)
        return
    check_keys(settings, baseline_algorithm(method.name))
    IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    resolve_policy_kwargs(settings.get("policy_kwargs") or {})


# --- the request and its plan ----------------------------------------------------------------------
@dataclass
class ReproduceRequest:
    """What the user asked of ``sb3_gccp reproduce``."""

    preset: str = "paper"
    overrides: dict[str, Any] = field(default_factory=dict)
    """Preset fields to replace (:meth:`Preset.with_overrides`)."""
    seeds: tuple[int, ...] = (0,)
    """Training seeds; with several, the tables give mean and sample std over them."""
    methods: tuple[str, ...] = tuple(METHODS)
    planner: Path | None = None
    """A trained motion-planner ``.zip`` for every hierarchy variant; None trains one per seed."""
    out: Path = Path("results")
    log_folder: Path = Path("runs")
    eval_seed: int = 0
    """First traffic seed of the evaluation episodes of every task."""
    torch_threads: int | None = 1
    """Torch threads of the learners (None: torch's default; the quick preset took 5x longer with 2
    threads than with 1 on a busy 2-core machine)."""
    progress_bar: bool = True
    argv: list[str] = field(default_factory=lambda: list(sys.argv))


@dataclass
class Plan:
    """A checked request: the preset, the methods and where everything goes."""

    request: ReproduceRequest
    preset: Preset
    methods: list[Method]
    root: Path
    """``<log_folder>/reproduce/<preset>``."""
    configs: dict[str, Path]
    """Zoo file of every method (and of the planner, under 'planner')."""

    @property
    def trains_planner(self) -> bool:
        """Whether a motion-planner is trained per seed."""
        return self.request.planner is None and any(m.is_hierarchy for m in self.methods)


def prepare(request: ReproduceRequest) -> Plan:
    """Check a request, write the methods' zoo files into ``<out>/configs`` and the preset into the
    reproduction's folder.

    :raises ValueError: bad input, with a one-line reason; nothing is written then
    """
    if request.preset not in PRESETS:
        raise ValueError(f"unknown preset {request.preset!r}: expected {' or '.join(PRESETS)}")
    unknown = [m for m in request.methods if m not in METHODS]
    if unknown or not request.methods:
        hints = [_with_hint(m, list(METHODS)) for m in unknown]
        raise ValueError(f"unknown method(s) {', '.join(hints) or '(none)'}: expected {', '.join(METHODS)}")
    if not request.seeds or len(set(request.seeds)) != len(request.seeds) or min(request.seeds) < 0:
        raise ValueError("--seeds must be distinct non-negative integers")
    if request.eval_seed < 0:
        raise ValueError("--eval-seed must be non-negative")
    if request.torch_threads is not None and request.torch_threads < 1:
        raise ValueError("--torch-threads must be at least 1")
    if request.planner is not None and request.planner != Path(SCRIPTED):
        if not request.planner.is_file():
            raise ValueError(f"planner not found: {request.planner} (give a planner .zip or 'scripted')")
        if not zipfile.is_zipfile(request.planner):
            raise ValueError(f"not an SB3 .zip: {request.planner}")
    preset = PRESETS[request.preset].with_overrides(request.overrides)
    methods = [m for m in METHODS.values() if m.name in request.methods]
    files: dict[str, dict[str, Any]] = {}
    for method in methods:
        entry = method_settings(method, preset)
        check_settings(method, entry)
        files[method.name] = {DECIDER_ENV_ID if method.is_hierarchy else FLAT_ENV_ID: entry}
    if request.planner is None and any(m.is_hierarchy for m in methods):
        entry = planner_settings(preset)
        check_settings(None, entry)
        files["planner"] = {PLANNER_ENV_ID: entry}
    root = request.log_folder / "reproduce" / request.preset
    _check_same_preset(root, preset)

    root.mkdir(parents=True, exist_ok=True)
    (root / "preset.yml").write_text(yaml.safe_dump(preset.to_dict(), sort_keys=True))
    (request.out / "configs").mkdir(parents=True, exist_ok=True)
    configs = {name: request.out / "configs" / f"{name}.yml" for name in files}
    for name, content in files.items():
        configs[name].write_text(yaml.safe_dump(content, sort_keys=False))
    return Plan(request, preset, methods, root, configs)


def _with_hint(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, 1)
    return f"{name!r} (did you mean {close[0]!r}?)" if close else repr(name)


def _check_same_preset(root: Path, preset: Preset) -> None:
    """Finished runs are reused only with the settings they were made with."""
    file = root / "preset.yml"
    if not file.is_file():
        return
    before = yaml.safe_load(file.read_text())
    now = preset.to_dict()
    changed = sorted(k for k in TRAINING_FIELDS if before.get(k) != now[k])
    if changed:
        raise ValueError(
            f"{root} holds runs of other preset settings ({', '.join(changed)} differ): "
            "give the same settings or another --log-folder"
        )


# --- training and evaluating one method ------------------------------------------------------------
TRAINING_FILE = "training.json"
EVALUATION_FILE = "evaluation.json"


def _finished(run_dir: Path) -> dict[str, Any] | None:
    file = run_dir / TRAINING_FILE
    return json.loads(file.read_text()) if file.is_file() else None


def train_planner_once(plan: Plan, seed: int, label: str) -> tuple[Path, dict[str, Any]]:
    """The seed's motion-planner: trained (or continued), or the finished one; its path and record."""
    run_dir = plan.root / f"seed{seed}" / "planner"
    record = _finished(run_dir)
    if record is not None:
        print(f"{label}: finished before, skipped", flush=True)
        return run_dir / "planner.zip", record
    print(f"{label}: training for {plan.preset.planner_timesteps:,} steps", flush=True)
    start = time.perf_counter()
    path = train_planner(_stage_request(plan, plan.configs["planner"], seed, run_dir, None))
    record = {
        **planner_budget(path, run_dir / "monitor"),
        "wall_clock_s": round(time.perf_counter() - start, 1),
    }
    (run_dir / TRAINING_FILE).write_text(json.dumps(record, indent=2) + "\n")
    print(f"{label}: trained {record['timesteps']:,} steps in {record['wall_clock_s']:.0f} s", flush=True)
    return path, record


def planner_budget(path: Path, monitor: Path | None) -> dict[str, Any]:
    """Steps a planner was trained for and, when its Monitor files are at hand, its episodes."""
    episodes = None
    if monitor is not None and monitor.is_dir():
        episodes = len(load_results(str(monitor)))
    if path == Path(SCRIPTED):
        return {"planner": SCRIPTED, "timesteps": 0, "episodes": 0}
    timesteps = int(MaskablePPO.load(path, device="cpu").num_timesteps)
    return {"planner": str(path), "timesteps": timesteps, "episodes": episodes}


def _stage_request(plan: Plan, config: Path, seed: int, run_dir: Path, planner: Path | None) -> StageRequest:
    """A training stage's request for a run in ``run_dir``: resumed if it started, else new there."""
    started = (run_dir / "config.yml").is_file()
    if run_dir.exists() and not started:  # made, but nothing written yet
        shutil.rmtree(run_dir)
    return StageRequest(
        config_file=config,
        seed=seed,
        resume=run_dir if started else None,
        run_dir=None if started else run_dir,
        progress_bar=plan.request.progress_bar,
        torch_threads=plan.request.torch_threads,
        planner=planner,
        argv=plan.request.argv,
    )


def train_method_once(
    plan: Plan, method: Method, seed: int, planner: Path | None, label: str
) -> dict[str, Any]:
    """Train a method for the preset's episodes unless its run finished before; return its record."""
    run_dir = plan.root / f"seed{seed}" / method.name
    record = _finished(run_dir)
    if record is not None:
        if method.is_hierarchy and planner is not None and not _same_planner(run_dir, planner):
            raise ValueError(
                f"{run_dir} was trained over another planner than {planner}: "
                "give the same --planner or another --log-folder"
            )
        print(f"{label}: finished before, skipped", flush=True)
        return record
    print(f"{label}: training for {plan.preset.episodes:,} episodes", flush=True)
    start = time.perf_counter()
    if method.is_hierarchy:
        _train_hierarchy(plan, method, seed, planner, run_dir)
    else:
        _train_baseline(plan, method, seed, run_dir, label)
    history = read_episodes(run_dir / "episodes.csv")
    record = {
        "method": method.name,
        "seed": seed,
        "episodes": len(history),
        "timesteps": history[-1]["timesteps"] if history else 0,
        "wall_clock_s": round(time.perf_counter() - start, 1),
    }
    (run_dir / TRAINING_FILE).write_text(json.dumps(record, indent=2) + "\n")
    print(f"{label}: trained {record['episodes']} episodes in {record['wall_clock_s']:.0f} s", flush=True)
    return record


def _same_planner(run_dir: Path, planner: Path) -> bool:
    """Whether a finished hierarchy run was trained over ``planner`` (a ``.zip`` or 'scripted')."""
    trained = run_dir / "planner.zip"
    if planner == Path(SCRIPTED):
        return not trained.is_file()
    return trained.is_file() and filecmp.cmp(trained, planner, False)


def _train_hierarchy(plan: Plan, method: Method, seed: int, planner: Path | None, run_dir: Path) -> None:
    train_decider(_stage_request(plan, plan.configs[method.name], seed, run_dir, planner))


def _train_baseline(plan: Plan, method: Method, seed: int, run_dir: Path, label: str) -> None:
    resume = has_checkpoint(run_dir)
    if resume:
        print(f"{label}: continuing from the last checkpoint", flush=True)
    elif run_dir.exists():
        print(f"{label}: an unfinished run without a checkpoint starts over", flush=True)
        shutil.rmtree(run_dir)
    if plan.request.torch_threads is not None:
        th.set_num_threads(plan.request.torch_threads)
    train_baseline(
        method.name,
        plan.configs[method.name],
        run_dir,
        seed,
        plan.preset.episodes,
        progress_bar=plan.request.progress_bar,
        description=label,
        resume=resume,
    )


def evaluate_once(plan: Plan, method: Method, seed: int, label: str) -> dict[str, Any]:
    """The method's evaluation on the preset's flows per task: computed, or read if it was before."""
    run_dir = plan.root / f"seed{seed}" / method.name
    key = {"eval_seed": plan.request.eval_seed, "episodes_per_task": plan.preset.episodes_per_task}
    file = run_dir / EVALUATION_FILE
    if file.is_file():
        saved = json.loads(file.read_text())
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    print(f"{label}: evaluating on {plan.preset.episodes_per_task} traffic flow(s) per task", flush=True)
    env, policy = _evaluation_env_and_policy(method, run_dir)
    results = evaluate(
        env, policy, TASKS, plan.preset.episodes_per_task, plan.request.eval_seed, plan.request.progress_bar
    )
    saved = {**key, "table": summarize(results), "episodes": [asdict(r) for r in results]}
    file.write_text(json.dumps(saved, indent=1) + "\n")
    overall = saved["table"]["overall"]
    print(f"{label}: success {overall['success']:.1f} %, collision {overall['crashed']:.1f} %", flush=True)
    return saved


def _evaluation_env_and_policy(method: Method, run_dir: Path) -> tuple[Any, Any]:
    if method.is_hierarchy:
        hierarchy = load_hierarchy(run_dir)
        return hierarchy.make_env(), hierarchy.decider_policy()
    if not (run_dir / BASELINE_FILE).is_file():  # trained before baseline runs named their algorithm
        write_baseline_spec(run_dir, method.name)
    env, policy, _ = load_baseline(run_dir)
    return env, policy


def predictor_errors_once(plan: Plan, seed: int) -> dict[str, Any]:
    """Fig. 7's numbers for a seed: ADE/FDE of ours's, the no-goal ablation's and the CV predictor on
    decisions ours drives on held-out traffic seeds; computed once."""
    seed_dir = plan.root / f"seed{seed}"
    predictors = {"learned": seed_dir / "ours" / "predictor.pt"}
    if any(m.name == "without_goal" for m in plan.methods):
        predictors["no_goal"] = seed_dir / "without_goal" / "predictor.pt"
    key = {
        "eval_seed": plan.request.eval_seed,
        "heldout_episodes": plan.preset.heldout_episodes,
        "predictors": sorted(predictors),
    }
    file = seed_dir / "predictor_errors.json"
    if file.is_file():
        saved = json.loads(file.read_text())
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    hierarchy = load_hierarchy(seed_dir / "ours")
    world = IntersectionConfig.from_dict(dict(hierarchy.world))
    per_episode = math.ceil(world.duration / (world.decision_period * DT)) + 1
    buffer = EpisodeReplayBuffer(capacity=plan.preset.heldout_episodes * per_episode)
    rng = np.random.default_rng(plan.request.eval_seed + HELDOUT_SEED_OFFSET)
    decisions = collect_decisions(
        hierarchy.make_env(), hierarchy.decider_policy(), plan.preset.heldout_episodes, buffer, rng
    )
    models = {name: load_predictor(path) for name, path in predictors.items()}
    errors = {
        name: displacement_errors(model, buffer)
        for name, model in {**models, "cv": ConstantVelocityPredictor()}.items()
    }
    saved = {**key, "decisions": decisions, "errors": errors}
    file.write_text(json.dumps(saved, indent=2) + "\n")
    return saved


# --- the whole reproduction ------------------------------------------------------------------------
def reproduce(plan: Plan) -> dict[str, Any]:
    """Train and evaluate every method for every seed, then write the tables, data and figures.

    :return: what ``results.json`` holds
    """
    started = time.perf_counter()
    if plan.request.torch_threads is None:  # loading a frozen policy sets one thread: keep the learners'
        plan = dataclasses.replace(
            plan, request=dataclasses.replace(plan.request, torch_threads=th.get_num_threads())
        )
    request = plan.request
    total = len(request.seeds) * (len(plan.methods) + int(plan.trains_planner))
    step = 0
    runs: dict[str, dict[int, dict[str, Any]]] = {m.name: {} for m in plan.methods}
    planners: dict[int, dict[str, Any]] = {}
    for seed in request.seeds:
        planner = request.planner
        if plan.trains_planner:
            step += 1
            planner, planners[seed] = train_planner_once(plan, seed, f"[{step}/{total}] seed {seed} planner")
        elif planner is not None:
            planners[seed] = {**planner_budget(planner, None), "given": True}
        for method in plan.methods:
            step += 1
            label = f"[{step}/{total}] seed {seed} {method.name}"
            training = train_method_once(plan, method, seed, planner, label)
            evaluation = evaluate_once(plan, method, seed, label)
            runs[method.name][seed] = {
                "run_dir": str(plan.root / f"seed{seed}" / method.name),
                "training": training,
                "table": evaluation["table"],
            }
    errors = {}
    if "ours" in runs:
        errors = {seed: predictor_errors_once(plan, seed) for seed in request.seeds}
    results = {
        "preset": request.preset,
        "settings": plan.preset.to_dict(),
        "seeds": list(request.seeds),
        "eval_seed": request.eval_seed,
        "episodes_per_task": plan.preset.episodes_per_task,
        "budget": {
            "episodes_per_method": plan.preset.episodes,
            "mask_after_episodes": mask_after_episodes(plan.preset),
            "planner_pretraining": {str(s): p for s, p in planners.items()},
        },
        "methods": {
            name: {"label": METHODS[name].label, "runs": {str(s): r for s, r in seed_runs.items()}}
            for name, seed_runs in runs.items()
        },
        "tables": {
            name: aggregate([r["table"] for r in seed_runs.values()]) for name, seed_runs in runs.items()
        },
        "predictor_errors": {str(s): e for s, e in errors.items()},
        "paper": {
            name: dict(zip((*TASKS, "overall"), rows, strict=True)) for name, rows in PAPER_RESULTS.items()
        },
    }
    write_outputs(plan, runs, errors)
    results["wall_clock_s"] = round(time.perf_counter() - started, 1)
    (request.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


# --- outputs ---------------------------------------------------------------------------------------
RATES = ("success", "crashed", "offroad", "wrong_exit", "timeout")


def aggregate(tables: Sequence[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean and sample standard deviation over seeds of every rate of :func:`~sb3_gccp.evaluation.summarize`
    tables (std 0 with one seed)."""
    result: dict[str, dict[str, dict[str, float]]] = {}
    for task in tables[0]:
        result[task] = {}
        for rate in RATES:
            values = np.array([t[task][rate] for t in tables])
            std = float(values.std(ddof=1)) if len(values) > 1 else 0.0
            result[task][rate] = {"mean": float(values.mean()), "std": std}
    return result


def _spread(values: Sequence[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{np.mean(values):.1f}±{np.std(values, ddof=1):.1f}"


def format_results_table(rows: Sequence[tuple[str, Sequence[Mapping[str, Mapping[str, float]]]]]) -> str:
    """The paper's table: per method (a label and its summary table per training seed), success /
    collision [%] per task and overall, and the overall timeout share; mean±std over several seeds."""
    lines = [
        "| method | left S/C | straight S/C | right S/C | overall S/C | timeout % |",
        "|---|---|---|---|---|---|",
    ]
    for label, tables in rows:
        cells = [
            " / ".join(_spread([t[task][rate] for t in tables]) for rate in ("success", "crashed"))
            for task in (*TASKS, "overall")
        ]
        cells.append(_spread([t["overall"]["timeout"] for t in tables]))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_paper_table(names: Sequence[str]) -> str:
    """The paper's own figures for these methods, in the same layout."""
    lines = [
        "| method | left S/C | straight S/C | right S/C | overall S/C |",
        "|---|---|---|---|---|",
    ]
    for name in names:
        cells = [f"{s:g} / {c:g}" for s, c in PAPER_RESULTS[name]]
        lines.append(f"| {METHODS[name].label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


TABLE_TITLES = {
    "table1": ("Table I: the baselines and ours", TABLE_1),
    "table2": ("Table II: ablations of GCCP", TABLE_2),
}


def write_outputs(
    plan: Plan,
    runs: Mapping[str, Mapping[int, Mapping[str, Any]]],
    errors: Mapping[int, Mapping[str, Any]],
) -> None:
    """Tables, CSV and figures into ``<out>`` (results.json is written by the caller)."""
    out = plan.request.out
    for stem, (title, names) in TABLE_TITLES.items():
        present = [n for n in names if n in runs]
        if present:
            (out / f"{stem}.md").write_text(_table_document(plan, title, present, runs))
            print(f"wrote {out / f'{stem}.md'}", flush=True)
    _write_csv(runs, out / "results.csv")
    curves = {
        name: [_success_history(Path(r["run_dir"])) for r in seed_runs.values()]
        for name, seed_runs in runs.items()
    }
    for stem, names, title in (
        ("fig5_baselines", TABLE_1, "Ours vs the baselines"),
        ("fig6_ablations", TABLE_2, "Ours vs the ablations"),
    ):
        present = [n for n in names if n in curves]
        if present:
            # Every hierarchy variant with a predictor switches its masks on at N_m.
            hierarchy = any(METHODS[n].predictor not in (None, "none") for n in present)
            plot_success_curves(
                {n: curves[n] for n in present},
                out / f"{stem}.png",
                title,
                mask_after_episodes(plan.preset) if hierarchy else None,
            )
    if errors:
        plot_predictor_errors([e["errors"] for e in errors.values()], out / "fig7_predictor_errors.png")
        _plot_predictions(plan, out / "fig8_predictions.png")
    print(f"wrote {out / 'results.csv'} and the figures", flush=True)


def _table_document(
    plan: Plan, title: str, names: Sequence[str], runs: Mapping[str, Mapping[int, Mapping[str, Any]]]
) -> str:
    request, preset = plan.request, plan.preset
    seeds = ", ".join(map(str, request.seeds))
    spread = " (mean±std over the training seeds)" if len(request.seeds) > 1 else ""
    rows = [(METHODS[n].label, [r["table"] for r in runs[n].values()]) for n in names]
    world = IntersectionConfig.from_dict(dict(preset.world))
    return "\n".join(
        [
            f"# {title}",
            "",
            f"Preset `{request.preset}`: every method trained for {preset.episodes:,} episodes (training "
            f"seeds {seeds}), evaluated on {preset.episodes_per_task} seeded traffic flow(s) per task from "
            f"seed {request.eval_seed}. Cells: success / collision rate [%]{spread}; timeout: episodes that "
            f"reached the {world.duration:g} s limit [%], overall. The rest of each row are off-road and "
            "wrong-exit episodes (results.csv).",
            "",
            format_results_table(rows),
            "",
            "The paper's figures (SMARTS, 50 flows per task):",
            "",
            format_paper_table(names),
            "",
        ]
    )


def _write_csv(runs: Mapping[str, Mapping[int, Mapping[str, Any]]], path: Path) -> None:
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["method", "label", "seed", "task", "episodes", *RATES])
        for name, seed_runs in runs.items():
            for seed, run in seed_runs.items():
                for task, row in run["table"].items():
                    rates = [f"{row[r]:.2f}" for r in RATES]
                    writer.writerow([name, METHODS[name].label, seed, task, int(row["episodes"]), *rates])


def _success_history(run_dir: Path) -> list[int]:
    return [row["success"] for row in read_episodes(run_dir / "episodes.csv")]


def plot_success_curves(
    curves: Mapping[str, Sequence[Sequence[int]]], path: Path, title: str, mask_after: int | None
) -> None:
    """Figs. 5 and 6: the rolling success rate per training episode of each method (mean over seeds,
    the band from the lowest to the highest seed).

    :param curves: per method name, the per-episode success (0/1) of each training seed
    :param mask_after: where the GCCP masks came on (a dashed line), if any
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 4))
    for name, runs in curves.items():
        rates = [rolling_rate(list(run), CURVE_WINDOW) for run in runs if len(run)]
        if not rates:
            continue
        length = min(len(r) for r in rates)
        stack = np.stack([r[:length] for r in rates])
        episodes = np.arange(1, length + 1)
        color = CURVE_COLORS[name]
        ax.plot(
            episodes, stack.mean(0), color=color, label=METHODS[name].label, lw=2 if name == "ours" else 1.2
        )
        if len(rates) > 1:
            ax.fill_between(episodes, stack.min(0), stack.max(0), color=color, alpha=0.2)
    if mask_after is not None:
        ax.axvline(mask_after, color="black", lw=0.8, ls="--", label="GCCP masks on")
    ax.set_xlabel("training episode")
    ax.set_ylabel(f"success rate (last {CURVE_WINDOW} episodes)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


PREDICTOR_LABELS = {
    "learned": "goal-conditioned (ours)",
    "no_goal": "w/o goal condition",
    "cv": "constant velocity",
}


def plot_predictor_errors(per_seed: Sequence[Mapping[str, Mapping[str, float]]], path: Path) -> None:
    """Fig. 7: ADE and FDE at 1 s of each predictor over all vehicles, the ego and the neighbours
    (bars: mean over seeds; whiskers: std when there are several)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in PREDICTOR_LABELS if n in per_seed[0]]
    groups = (("", "all vehicles"), ("ego_", "ego"), ("neighbour_", "neighbours"))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, metric in zip(axes, ("ade", "fde"), strict=True):
        for i, name in enumerate(names):
            values = np.array([[seed[name][f"{g}{metric}"] for g, _ in groups] for seed in per_seed])
            std = np.nanstd(values, 0, ddof=1) if len(values) > 1 else None
            x = np.arange(len(groups)) + (i - (len(names) - 1) / 2) * width
            ax.bar(x, np.nanmean(values, 0), width, yerr=std, capsize=3, label=PREDICTOR_LABELS[name])
        ax.set_xticks(np.arange(len(groups)), [label for _, label in groups])
        ax.set_ylabel(f"{metric.upper()} at 1 s [m]")
        ax.grid(alpha=0.3, axis="y")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(names), fontsize=8)
    fig.suptitle("Trajectory prediction on held-out decisions of ours")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_predictions(plan: Plan, path: Path) -> None:
    """Fig. 8: ours's predictor (first seed) in one scene per task, two subgoals each."""
    hierarchy = load_hierarchy(plan.root / f"seed{plan.request.seeds[0]}" / "ours")
    assert hierarchy.predictor_weights is not None
    world = IntersectionConfig.from_dict(dict(hierarchy.world))
    predictor = load_predictor(hierarchy.predictor_weights)
    decider = hierarchy.decider_policy()
    plot_scene(
        predictor, world, plan.request.eval_seed, path, hierarchy.planner, tasks=TASKS, decider=decider
    )
