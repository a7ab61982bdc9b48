"""A trained hierarchy on disk: decision-maker, motion-planner and GCCP module, ready to evaluate.

A decider run folder (and ``pretrained/``) holds a ``hierarchy.yml`` naming its files::

    planner: planner.zip          # or "scripted" (the scripted pure-pursuit planner)
    decider: decider.zip
    predictor: learned            # learned, no_goal, cv or none (w/o GCCP)
    predictor_weights: predictor.pt
    mask_margin: 0.0              # the GCCP collision check (GCCPCheck): box margin [m],
    mask_extrapolate_steps: 0     #   steps beyond T_f,
    mask_ego_deceleration: null   #   the ego braking in them [m/s^2] (null: it goes on),
    mask_yield_margin: null       #   neighbours waiting for the ego checked where they stand, with this
                                  #   margin [m] (null: along their prediction),
    mask_fallback_margin: null    #   the margin [m] of a second check when none passes (null: hold),
    mask_vehicle_sizes: simulator #   the boxes' sizes: the simulator's cars, or builtin (5 x 2 m);
                                  #   each optional
    world: {...}                  # the world config the decider was trained on
    overrides:                    # optional: settings the decider was NOT trained with
      world: {...}                #   world keys replacing those above
      mask: {...}                 #   GCCP check settings replacing those above

``planner``, ``decider``, ``predictor`` and ``world`` are required, and ``predictor_weights`` with a
learned predictor; the files named must lie inside the folder (no absolute path, no ``..``). Every
setting above ``overrides`` is one the decision-maker was trained with. A hierarchy with
``overrides`` (written by ``sb3_gccp export --set/--mask``) runs only when asked explicitly
(``allow_overrides``, the CLI's ``--allow-overrides``): a result it gives is not the trained system's.
:class:`Hierarchy` is the one reader and writer of this file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gccp_envs.config import IntersectionConfig, drop_retired_keys
from gccp_envs.option_env import GCCPDeciderEnv
from sb3_gccp.constants import DECIDER_FILE, HIERARCHY_FILE, PLANNER_FILE, SCRIPTED
from sb3_gccp.frozen import FrozenPolicy, load_decider, load_planner
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor, check_predictor_world, load_predictor
from sb3_gccp.gccp.settings import CHECK_KEYS, LEARNED, PREDICTORS, RETIRED_CHECK_KEYS, GCCPCheck
from sb3_gccp.hyperparams import read_yaml_mapping
from sb3_gccp.safe_loading import file_in_folder
from sb3_gccp.training.checkpoints import write_atomically

OVERRIDES = "overrides"
"""The ``hierarchy.yml`` section of settings the decider was not trained with: ``world`` and ``mask``."""
CHECK_OVERRIDES = "GCCP check: "
"""How messages name a GCCP check setting that replaces a trained one."""
KEYS = ("planner", "decider", "predictor", "predictor_weights", *CHECK_KEYS, "world", OVERRIDES)
"""The keys of ``hierarchy.yml``, in the order they are written."""
REQUIRED_KEYS = ("planner", "decider", "predictor", "world")
"""The keys every ``hierarchy.yml`` has (``predictor_weights`` too with a learned predictor)."""


@dataclass(frozen=True)
class Hierarchy:
    """A trained hierarchy: what its ``hierarchy.yml`` says, and the folder its files are in.

    The file names are relative to ``folder``; :attr:`world` and :attr:`check` are the settings the
    hierarchy runs with, the trained ones with the overrides applied.
    """

    folder: Path
    """The folder of ``hierarchy.yml`` and of the files it names."""
    decider_file: str = DECIDER_FILE
    """The decision-maker (MaskablePPO ``.zip``)."""
    planner_file: str = PLANNER_FILE
    """The motion-planner (MaskablePPO ``.zip``), or ``scripted`` for the scripted planner."""
    predictor: str = "none"
    """The GCCP variant: learned, no_goal, cv or none (w/o GCCP)."""
    predictor_weights_file: str | None = None
    """The predictor's weights (learned variants)."""
    trained_check: GCCPCheck = field(default_factory=GCCPCheck)
    """The GCCP check the decider was trained with."""
    trained_world: Mapping[str, Any] = field(default_factory=dict)
    """The world config keys the decider was trained on."""
    world_overrides: Mapping[str, Any] = field(default_factory=dict)
    """World config keys the decider was not trained with, replacing ``trained_world``'s."""
    mask_overrides: Mapping[str, Any] = field(default_factory=dict)
    """GCCP check keys (``mask_*``) the decider was not trained with, replacing ``trained_check``'s."""

    def __post_init__(self) -> None:
        if self.mask_overrides and self.predictor == "none":
            raise ValueError(f"{self.folder} has no GCCP module (predictor: none): there is no check to set")
        if self.mask_overrides:
            self.trained_check.replace(self.mask_overrides, CHECK_OVERRIDES)  # one line on a bad value

    # --- the file ------------------------------------------------------------------------------
    @classmethod
    def read(cls, path: str | Path) -> Hierarchy:
        """The hierarchy of a run folder, ``pretrained/``, or a decider ``.zip`` inside one (which then
        takes the place of the file's decider).

        :raises ValueError: with a one-line reason when something is missing or a setting is bad
        """
        path = Path(path)
        if not path.exists():
            raise ValueError(f"model not found: {path}")
        folder = path.parent if path.is_file() else path
        spec_file = folder / HIERARCHY_FILE
        if not spec_file.is_file():
            raise ValueError(
                f"no {HIERARCHY_FILE} in {folder}: give a decider run folder or a decider .zip in one"
            )
        hierarchy = cls.from_dict(read_yaml_mapping(spec_file, "hierarchy file"), folder, str(spec_file))
        if path.is_file():
            hierarchy = dataclasses.replace(hierarchy, decider_file=path.name)
        files = {
            "decider": hierarchy.decider_file,
            "planner": None if hierarchy.planner is None else hierarchy.planner_file,
            "predictor_weights": hierarchy.predictor_weights_file,
        }
        for key, name in files.items():
            if name is not None and not file_in_folder(folder, name, f"{spec_file}: {key}").is_file():
                raise ValueError(f"{spec_file} names a missing file: {folder / name}")
        return hierarchy

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any], folder: Path, where: str = HIERARCHY_FILE) -> Hierarchy:
        """A hierarchy from the map of its ``hierarchy.yml`` (no file is looked at).

        :param where: how messages name the file
        :raises ValueError: one line naming an unknown key or section, or a bad setting
        """
        spec = drop_retired_keys(spec, RETIRED_CHECK_KEYS, f"{where}: GCCP check")
        unknown = sorted(set(spec) - set(KEYS))
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}: expected {', '.join(KEYS)}")
        missing = [key for key in REQUIRED_KEYS if key not in spec]
        if missing:
            raise ValueError(f"{where}: missing key(s) {', '.join(missing)}")
        predictor = str(spec.get("predictor", "none"))
        if predictor not in PREDICTORS:
            raise ValueError(f"{where}: predictor must be one of {', '.join(PREDICTORS)}, got {predictor!r}")
        overrides = spec.get(OVERRIDES) or {}
        if not isinstance(overrides, Mapping) or set(overrides) - {"world", "mask"}:
            raise ValueError(f"{where}: {OVERRIDES} must be a map with the keys world and mask")
        world_overrides = dict(overrides.get("world") or {})
        mask_overrides = drop_retired_keys(
            overrides.get("mask") or {}, RETIRED_CHECK_KEYS, f"{where}: GCCP check"
        )
        unknown = sorted(set(mask_overrides) - set(CHECK_KEYS))
        if unknown:
            raise ValueError(f"{where}: unknown GCCP check key(s) in {OVERRIDES}.mask: {', '.join(unknown)}")
        weights = spec.get("predictor_weights")
        if not isinstance(spec["world"], Mapping):
            raise ValueError(f"{where}: world must be a map of world config keys")
        if predictor in LEARNED and weights is None:
            raise ValueError(f"{where}: a {predictor} predictor needs predictor_weights")
        check = GCCPCheck.from_dict({k: v for k, v in spec.items() if k in CHECK_KEYS}, f"{where}: ")
        return cls(
            folder,
            str(spec["decider"]),
            str(spec["planner"]),
            predictor,
            str(weights) if predictor in LEARNED else None,
            check,
            dict(spec["world"]),
            world_overrides,
            mask_overrides,
        )

    def to_dict(self) -> dict[str, Any]:
        """The map of ``hierarchy.yml`` (plain data; ``overrides`` only when there are some)."""
        spec = {
            "planner": self.planner_file,
            "decider": self.decider_file,
            "predictor": self.predictor,
            "predictor_weights": self.predictor_weights_file,
            **self.trained_check.to_dict(),
            "world": _plain(self.trained_world),
        }
        if self.overrides:
            spec[OVERRIDES] = self.overrides
        return spec

    def to_yaml(self) -> str:
        """The text of ``hierarchy.yml``."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def write(self) -> Path:
        """Write ``hierarchy.yml`` into the hierarchy's folder (whole or not at all); return the file."""
        path = self.folder / HIERARCHY_FILE
        text = self.to_yaml()
        write_atomically(path, lambda temporary: temporary.write_text(text))
        return path

    # --- the settings it runs with -------------------------------------------------------------
    @property
    def overrides(self) -> dict[str, Any]:
        """The ``overrides`` section: its non-empty maps of ``world`` and ``mask`` keys."""
        sections = {"world": _plain(self.world_overrides), "mask": dict(self.mask_overrides)}
        return {name: values for name, values in sections.items() if values}

    @property
    def world(self) -> dict[str, Any]:
        """The world config keys it runs on: the trained ones with the world overrides applied."""
        return {**self.trained_world, **self.world_overrides}

    @property
    def check(self) -> GCCPCheck:
        """The GCCP check it runs: the trained one with the mask overrides applied."""
        if not self.mask_overrides:
            return self.trained_check
        return self.trained_check.replace(self.mask_overrides, CHECK_OVERRIDES)

    def with_overrides(
        self, world: Mapping[str, Any] | None = None, mask: Mapping[str, Any] | None = None
    ) -> Hierarchy:
        """This hierarchy with more settings it was not trained with (added to its ``overrides``).

        :param world: world config keys
        :param mask: GCCP check keys (``mask_*``)
        :raises ValueError: one line naming an unknown key or a bad value
        """
        hierarchy = dataclasses.replace(
            self,
            world_overrides={**self.world_overrides, **(world or {})},
            mask_overrides={**self.mask_overrides, **(mask or {})},
        )
        IntersectionConfig.from_dict(hierarchy.world)
        return hierarchy

    # --- its files -----------------------------------------------------------------------------
    @property
    def decider(self) -> Path:
        """The decision-maker's ``.zip``."""
        return self.folder / self.decider_file

    @property
    def planner(self) -> Path | None:
        """The motion-planner's ``.zip``; ``None`` for the scripted planner."""
        return None if self.planner_file == SCRIPTED else self.folder / self.planner_file

    @property
    def predictor_weights(self) -> Path | None:
        """The predictor's weights (learned variants)."""
        return None if self.predictor_weights_file is None else self.folder / self.predictor_weights_file

    # --- what it runs --------------------------------------------------------------------------
    def make_env(
        self,
        overrides: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        trusted: bool = False,
    ) -> GCCPDeciderEnv:
        """The option env with the frozen planner and the GCCP mask, on the hierarchy's world config;
        the planner and the predictor are checked against that world before it is built.

        :param overrides: world config keys replacing the hierarchy's for this env only
        :param trusted: load the planner through ``MaskablePPO.load`` (which runs code pickled in it)
        :raises ValueError: one line, when a file cannot be read or does not fit the world
        """
        world = IntersectionConfig.from_dict({**self.world, **(overrides or {})})
        return GCCPDeciderEnv(
            world,
            planner=None if self.planner is None else load_planner(self.planner, world, trusted),
            mask_fn=self.mask_fn(world),
            render_mode=render_mode,
        )

    def mask_fn(self, world: IntersectionConfig | None = None) -> GCCPMask | None:
        """The GCCP module of this hierarchy (``None`` without GCCP), its predictor checked against
        ``world`` (default: the hierarchy's)."""
        if self.predictor == "none":
            return None
        world = world or IntersectionConfig.from_dict(self.world)
        if self.predictor == "cv":
            return self.check.make_mask(ConstantVelocityPredictor(), world)
        assert self.predictor_weights is not None
        predictor = load_predictor(self.predictor_weights)
        check_predictor_world(predictor, world, self.predictor_weights)
        return self.check.make_mask(predictor, world)

    def decider_policy(
        self, world: IntersectionConfig, deterministic: bool = True, trusted: bool = False
    ) -> FrozenPolicy:
        """The decision-maker for an option env on ``world`` (``env.config``), checked against it: its
        most likely subgoal, or (``deterministic=False``) one sampled.

        :param trusted: load it through ``MaskablePPO.load`` (which runs code pickled in it)
        :raises ValueError: one line, when the file cannot be read or does not fit the world
        """
        return load_decider(self.decider, world, deterministic, trusted)


def load_hierarchy(
    path: str | Path, mask: Mapping[str, Any] | None = None, allow_overrides: bool = False
) -> Hierarchy:
    """Read a hierarchy to run it, from a run folder, ``pretrained/``, or a decider ``.zip`` inside one.

    :param mask: GCCP check settings (``mask_*`` keys) replacing those of ``hierarchy.yml``, for
        example ``{"mask_margin": 0.5}`` to evaluate the trained decider under another check
    :param allow_overrides: run the settings of an ``overrides`` section (which the decider was not
        trained with); without it such a hierarchy is refused
    :raises ValueError: with a one-line reason when something is missing or a setting is bad
    """
    hierarchy = Hierarchy.read(path)
    if hierarchy.overrides and not allow_overrides:
        names = [f"{section}.{key}" for section, values in hierarchy.overrides.items() for key in values]
        raise ValueError(
            f"{hierarchy.folder / HIERARCHY_FILE} runs settings the decider was not trained with "
            f"({OVERRIDES}: {', '.join(names)}): pass --allow-overrides to run them"
        )
    return hierarchy.with_overrides(mask=mask) if mask else hierarchy


def _plain(values: Mapping[str, Any]) -> dict[str, Any]:
    """A world config map as YAML takes it (tuples as lists)."""
    return {key: list(value) if isinstance(value, tuple) else value for key, value in values.items()}
