"""A trained hierarchy on disk: decision-maker, motion-planner and GCCP module, ready to evaluate.

A decider run folder (and ``pretrained/``) holds a ``hierarchy.yml`` naming its files::

    planner: planner.zip          # or "scripted" (the scripted pure-pursuit planner)
    decider: decider.zip
    predictor: learned            # learned, no_goal, cv or none (w/o GCCP)
    predictor_weights: predictor.pt
    mask_margin: 0.0              # GCCP collision check: box margin [m] and steps beyond T_f
    mask_extrapolate_steps: 0     #   (both optional, 0 if absent)
    mask_ego_deceleration: null   # the ego brakes in those steps [m/s^2] (optional; null: goes on)
    mask_yield_margin: null       # neighbours waiting for the ego checked where they stand, with this
                                  #   margin [m] (optional; null: along their prediction)
    world: {...}                  # the world config the decider was trained on
    overrides:                    # optional: settings the decider was NOT trained with
      world: {...}                #   world keys replacing those above
      mask: {...}                 #   GCCP check settings replacing those above

Every setting above ``overrides`` is one the decision-maker was trained with. A hierarchy with
``overrides`` (written by ``sb3_gccp export --set/--mask``) runs only when asked explicitly
(``allow_overrides``, the CLI's ``--allow-overrides``): a result it gives is not the trained system's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gccp_envs.config import IntersectionConfig, require_int, require_non_negative, require_positive
from gccp_envs.option_env import GCCPDeciderEnv
from sb3_gccp.callbacks import LEARNED, PREDICTORS
from sb3_gccp.collision import CollisionChecker
from sb3_gccp.frozen import FrozenPolicy
from sb3_gccp.hyperparams import read_yaml_mapping
from sb3_gccp.prediction import ConstantVelocityPredictor, GCCPMask, load_predictor

HIERARCHY_FILE = "hierarchy.yml"
SCRIPTED = "scripted"
"""The planner name of a hierarchy whose options run the scripted planner (``gccp_envs.scripted``)."""


@dataclass(frozen=True)
class Hierarchy:
    """The files of a trained hierarchy."""

    decider: Path
    planner: Path | None
    """The planner ``.zip``; ``None`` for the scripted planner."""
    predictor: str
    predictor_weights: Path | None
    world: Mapping[str, Any] = field(default_factory=dict)
    mask_margin: float = 0.0
    mask_extrapolate_steps: int = 0
    mask_ego_deceleration: float | None = None
    mask_yield_margin: float | None = None
    overrides: Mapping[str, Any] = field(default_factory=dict)
    """The ``overrides`` map of ``hierarchy.yml`` (applied: ``world`` and the mask settings above hold
    the overridden values)."""

    def make_env(
        self, overrides: Mapping[str, Any] | None = None, render_mode: str | None = None
    ) -> GCCPDeciderEnv:
        """The option env with the frozen planner and the GCCP mask, on the training world config."""
        world = IntersectionConfig.from_dict({**self.world, **(overrides or {})})
        return GCCPDeciderEnv(
            world,
            planner=None if self.planner is None else FrozenPolicy(self.planner),
            mask_fn=self.mask_fn(),
            render_mode=render_mode,
        )

    def mask_fn(self) -> GCCPMask | None:
        """The GCCP module of this hierarchy (``None`` without GCCP)."""
        if self.predictor == "none":
            return None
        checker = CollisionChecker(margin=self.mask_margin)
        extrapolation = (self.mask_extrapolate_steps, self.mask_ego_deceleration, self.mask_yield_margin)
        if self.predictor == "cv":
            return GCCPMask(ConstantVelocityPredictor(), checker, *extrapolation)
        assert self.predictor_weights is not None
        return GCCPMask(load_predictor(self.predictor_weights), checker, *extrapolation)

    def decider_policy(self, deterministic: bool = True) -> FrozenPolicy:
        """The decision-maker: its most likely subgoal, or (``deterministic=False``) one sampled."""
        return FrozenPolicy(self.decider, deterministic=deterministic)


MASK_KEYS = ("mask_margin", "mask_extrapolate_steps", "mask_ego_deceleration", "mask_yield_margin")
"""The keys of ``hierarchy.yml`` that set the GCCP collision check (``load_hierarchy``'s ``mask``)."""


def _mask_settings(spec: Mapping[str, Any], where: str) -> tuple[float, int, float | None, float | None]:
    """The GCCP check settings (``MASK_KEYS``, in order) of a hierarchy spec.

    :raises ValueError: one line naming the key whose value is not of its kind
    """
    margin, steps = spec.get("mask_margin", 0.0), spec.get("mask_extrapolate_steps", 0)
    deceleration, yield_margin = spec.get("mask_ego_deceleration"), spec.get("mask_yield_margin")
    require_non_negative(f"{where}: mask_margin", margin)
    if yield_margin is not None:
        require_non_negative(f"{where}: mask_yield_margin", yield_margin)
    require_int(f"{where}: mask_extrapolate_steps", steps, minimum=0)
    if deceleration is not None:
        require_positive(f"{where}: mask_ego_deceleration", deceleration)
    return (
        float(margin),
        steps,
        None if deceleration is None else float(deceleration),
        None if yield_margin is None else float(yield_margin),
    )


OVERRIDES = "overrides"
"""The ``hierarchy.yml`` section of settings the decider was not trained with: ``world`` and ``mask``."""


def read_overrides(spec: Mapping[str, Any], where: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The world and GCCP check settings of a hierarchy spec's ``overrides`` (empty without one).

    :raises ValueError: one line naming an unknown section or check key
    """
    overrides = spec.get(OVERRIDES) or {}
    if not isinstance(overrides, Mapping) or set(overrides) - {"world", "mask"}:
        raise ValueError(f"{where}: {OVERRIDES} must be a map with the keys world and mask")
    world, mask = dict(overrides.get("world") or {}), dict(overrides.get("mask") or {})
    unknown = sorted(set(mask) - set(MASK_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown GCCP check key(s) in {OVERRIDES}.mask: {', '.join(unknown)}")
    return world, mask


def load_hierarchy(
    path: str | Path, mask: Mapping[str, Any] | None = None, allow_overrides: bool = False
) -> Hierarchy:
    """Read a hierarchy from a run folder, ``pretrained/``, or a decider ``.zip`` inside one.

    :param mask: GCCP check settings (keys of ``MASK_KEYS``) replacing those of ``hierarchy.yml``, for
        example ``{"mask_margin": 0.5}`` to evaluate the trained decider under another check
    :param allow_overrides: run the settings of an ``overrides`` section (which the decider was not
        trained with); without it such a hierarchy is refused
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
    spec = read_yaml_mapping(spec_file, "hierarchy file")
    predictor = str(spec.get("predictor", "none"))
    if predictor not in PREDICTORS:
        raise ValueError(f"{spec_file}: predictor must be one of {', '.join(PREDICTORS)}, got {predictor!r}")
    unknown = sorted(set(mask or {}) - set(MASK_KEYS))
    if unknown:
        raise ValueError(f"unknown GCCP check key(s) {', '.join(unknown)}: expected {', '.join(MASK_KEYS)}")
    world_overrides, mask_overrides = read_overrides(spec, str(spec_file))
    if (world_overrides or mask_overrides) and not allow_overrides:
        names = [f"world.{key}" for key in world_overrides] + [f"mask.{key}" for key in mask_overrides]
        raise ValueError(
            f"{spec_file} runs settings the decider was not trained with ({OVERRIDES}: {', '.join(names)}): "
            "pass --allow-overrides to run them"
        )
    if (mask or mask_overrides) and predictor == "none":
        raise ValueError(f"{folder} has no GCCP module (predictor: none): there is no check to set")
    settings = _mask_settings(spec, str(spec_file))
    if mask or mask_overrides:
        settings = _mask_settings({**spec, **mask_overrides, **(mask or {})}, "GCCP check")
    decider = path if path.is_file() else folder / str(spec.get("decider", "decider.zip"))
    name = str(spec.get("planner", "planner.zip"))
    planner = None if name == SCRIPTED else folder / name
    weights = folder / str(spec["predictor_weights"]) if predictor in LEARNED else None
    for needed in (decider, planner, weights):
        if needed is not None and not needed.is_file():
            raise ValueError(f"{spec_file} names a missing file: {needed}")
    return Hierarchy(
        decider,
        planner,
        predictor,
        weights,
        {**dict(spec.get("world") or {}), **world_overrides},
        *settings,
        {"world": world_overrides, "mask": mask_overrides} if world_overrides or mask_overrides else {},
    )
