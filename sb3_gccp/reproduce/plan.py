"""What a reproduction runs: the presets, the zoo entry of every method, and the checked request."""

from __future__ import annotations

import copy
import difflib
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gccp_envs.config import IntersectionConfig, reject_unknown_keys, require_int
from sb3_gccp.constants import DECIDER_ENV_ID, FLAT_ENV_ID, PLANNER_ENV_ID, SCRIPTED
from sb3_gccp.frozen import load_planner
from sb3_gccp.hyperparams import (
    check_keys,
    default_config_file,
    gradient_steps_per_timestep,
    load_hyperparams,
    resolve_policy_kwargs,
)
from sb3_gccp.networks import EncoderConfig
from sb3_gccp.reproduce.methods import METHODS, Method
from sb3_gccp.training.baselines import MASKS_KEY, baseline_algorithm, max_episode_steps, uses_masks
from sb3_gccp.training.decider import gccp_settings
from sb3_gccp.training.planner import IMITATION_KEY, imitation_settings
from sb3_gccp.training.run_folder import run_budget

PRESET_FILE = "preset.yml"
"""In a reproduction's folder: the preset settings its runs were made with."""
PLANNER_EXTRACTOR = "sb3_gccp.policies.PlannerFeaturesExtractor"
"""The baselines' features extractor, named in their zoo files: the preset's encoder goes to it."""


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
        groups = (
            "planner",
            "hierarchy",
            *dict.fromkeys(m.algorithm for m in METHODS.values() if not m.is_hierarchy),
        )
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
            "planner": {
                "n_steps": 256,
                "batch_size": 64,
                "imitation": {"expert_steps": 256, "epochs": 1, "dagger_rounds": 1, "dagger_steps": 128},
            },
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


def method_settings(method: Method, preset: Preset, zoo_file: Path | None = None) -> dict[str, Any]:
    """A method's zoo entry: ppo_mask.yml's decider entry with only the ``gccp`` schedule and predictor
    changed, or the baseline's ``GCCPFlat-v0`` entry capped at ``episodes`` full-length episodes.

    :param zoo_file: the file to take the entry from instead of the shipped one (``--config``)
    """
    if method.is_hierarchy:
        entry = _shipped_entry("ppo_mask.yml", DECIDER_ENV_ID, zoo_file)
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
    entry = _shipped_entry(f"{method.algorithm}.yml", FLAT_ENV_ID, zoo_file)
    if method.paper_style:
        entry[MASKS_KEY] = False
        entry["env_kwargs"] = {**(entry.get("env_kwargs") or {}), "wrong_exit_penalty": False}
    encoders: tuple[tuple[str, ...], ...] = ()
    if (entry.get("policy_kwargs") or {}).get("features_extractor_class") == PLANNER_EXTRACTOR:
        encoders = (("policy_kwargs", "features_extractor_kwargs", "encoder"),)
    entry = _customised(entry, preset, method.algorithm, encoders)
    # The episode budget ends training; n_timesteps only caps it (and places step schedules).
    world = IntersectionConfig.from_dict(entry.get("env_kwargs") or {})
    entry["n_timesteps"] = preset.episodes * max_episode_steps(world)
    return entry


def mask_after_episodes(preset: Preset) -> int:
    """N_m of the preset's hierarchy variants: the preset's, or else the decider entry's."""
    return gccp_settings(method_settings(METHODS["ours"], preset)).mask_after_episodes


def _shipped_entry(file: str, env_id: str, given: Path | None = None) -> dict[str, Any]:
    return copy.deepcopy(load_hyperparams(given or default_config_file(file), env_id))


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
        own = ("gccp",) if method is not None else (IMITATION_KEY,)
        run_budget(settings, own_keys=own)
        if method is not None:
            gccp_settings(settings)
        else:
            imitation_settings(settings)
        return
    algorithm = baseline_algorithm(method.algorithm, uses_masks(settings))
    check_keys({k: v for k, v in settings.items() if k != MASKS_KEY}, algorithm)
    gradient_steps_per_timestep(algorithm, settings)
    IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    resolve_policy_kwargs(settings.get("policy_kwargs") or {})


# --- the request and its plan ----------------------------------------------------------------------
@dataclass
class ReproduceRequest:
    """What the user asked of ``sb3_gccp reproduce``."""

    preset: str = "paper"
    overrides: dict[str, Any] = field(default_factory=dict)
    """Preset fields to replace (:meth:`Preset.with_overrides`)."""
    zoo_files: dict[str, Path] = field(default_factory=dict)
    """Method -> the zoo file its entry comes from instead of the shipped one (such as ``tune``'s)."""
    seeds: tuple[int, ...] = (0,)
    """Training seeds; with several, the tables give the mean and the min-max over them."""
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

    def to_dict(self) -> dict[str, Any]:
        """Plain data (strings, numbers, lists, maps), as a job on another process or machine takes it."""
        data = asdict(self)
        for name in ("planner", "out", "log_folder"):
            data[name] = None if data[name] is None else str(data[name])
        data["seeds"], data["methods"] = list(self.seeds), list(self.methods)
        data["zoo_files"] = {method: str(file) for method, file in self.zoo_files.items()}
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ReproduceRequest:
        """The request :meth:`to_dict` gave."""
        values = dict(data)
        for name in ("out", "log_folder"):
            values[name] = Path(values[name])
        values["planner"] = None if values["planner"] is None else Path(values["planner"])
        values["seeds"], values["methods"] = tuple(values["seeds"]), tuple(values["methods"])
        values["zoo_files"] = {method: Path(file) for method, file in (values.get("zoo_files") or {}).items()}
        return cls(**values)


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
    entries: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """What :meth:`write_configs` writes into ``configs`` (left out of :meth:`to_dict`: a job reads the
    files)."""

    def write_configs(self) -> None:
        """Write every zoo file of ``configs`` (the folder made if need be)."""
        for name, content in self.entries.items():
            self.configs[name].parent.mkdir(parents=True, exist_ok=True)
            self.configs[name].write_text(yaml.safe_dump(content, sort_keys=False))

    @property
    def trains_planner(self) -> bool:
        """Whether a motion-planner is trained per seed."""
        return self.request.planner is None and any(m.is_hierarchy for m in self.methods)

    def run_dir(self, seed: int, name: str) -> Path:
        """The run folder of a method (or of the planner, ``name`` 'planner') for a training seed."""
        return self.root / f"seed{seed}" / name

    def to_dict(self) -> dict[str, Any]:
        """Plain data: what a job needs to rebuild the plan in another process, on any machine that
        sees the same paths."""
        return {
            "request": self.request.to_dict(),
            "preset": self.preset.to_dict(),
            "methods": [m.name for m in self.methods],
            "root": str(self.root),
            "configs": {name: str(path) for name, path in self.configs.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Plan:
        """The plan :meth:`to_dict` gave, without checking it again."""
        return cls(
            ReproduceRequest.from_dict(data["request"]),
            Preset.from_dict(data["preset"]),
            [METHODS[name] for name in data["methods"]],
            Path(data["root"]),
            {name: Path(path) for name, path in data["configs"].items()},
        )


def prepare(request: ReproduceRequest, collect: bool = False) -> Plan:
    """Check a request, write the methods' zoo files into ``<out>/configs`` and the preset into the
    reproduction's folder.

    :param collect: only read finished runs: the preset is the one the reproduction's folder holds
        (``--set`` applied over it), and that folder must exist; nothing is written (the zoo files are
        written by :func:`~sb3_gccp.reproduce.collect.collect` once every run is found finished)
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
    given_planner = request.planner if request.planner != Path(SCRIPTED) else None
    if given_planner is not None and not given_planner.is_file():
        raise ValueError(f"planner not found: {request.planner} (give a planner .zip or 'scripted')")
    root = request.log_folder / "reproduce" / request.preset
    base = PRESETS[request.preset]
    if collect:
        if not (root / PRESET_FILE).is_file():
            raise ValueError(
                f"no runs to collect: {root / PRESET_FILE} not found (check --log-folder, --preset)"
            )
        base = Preset.from_dict(yaml.safe_load((root / PRESET_FILE).read_text()))
    preset = base.with_overrides(request.overrides)
    methods = [m for m in METHODS.values() if m.name in request.methods]
    files: dict[str, dict[str, Any]] = {}
    unknown_files = sorted(set(request.zoo_files) - set(request.methods))
    if unknown_files:
        raise ValueError(f"--config for method(s) not reproduced: {', '.join(unknown_files)}")
    for method in methods:
        entry = method_settings(method, preset, request.zoo_files.get(method.name))
        check_settings(method, entry)
        files[method.name] = {DECIDER_ENV_ID if method.is_hierarchy else FLAT_ENV_ID: entry}
        if given_planner is not None and method.is_hierarchy:  # a planner that does not fit fails here
            load_planner(given_planner, IntersectionConfig.from_dict(entry.get("env_kwargs") or {}))
    if request.planner is None and any(m.is_hierarchy for m in methods):
        entry = planner_settings(preset)
        check_settings(None, entry)
        files["planner"] = {PLANNER_ENV_ID: entry}
    _check_same_preset(root, preset)
    if request.out.exists() and not request.out.is_dir():
        raise ValueError(f"--out {request.out}: a file, not a folder")

    configs = {name: request.out / "configs" / f"{name}.yml" for name in files}
    plan = Plan(request, preset, methods, root, configs, files)
    if not collect:
        root.mkdir(parents=True, exist_ok=True)
        (root / PRESET_FILE).write_text(yaml.safe_dump(preset.to_dict(), sort_keys=True))
        plan.write_configs()
    return plan


def _with_hint(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, 1)
    return f"{name!r} (did you mean {close[0]!r}?)" if close else repr(name)


def _check_same_preset(root: Path, preset: Preset) -> None:
    """Finished runs are reused only with the settings they were made with."""
    file = root / PRESET_FILE
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
