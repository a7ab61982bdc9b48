"""The GCCP module's settings: the collision check (:class:`GCCPCheck`) and the decider stage's
schedule and predictor training (:class:`GCCPSettings`, the ``gccp`` map of a zoo entry).

:class:`GCCPCheck` is the one home of the six ``mask_*`` settings: their defaults, their validation,
their YAML form (the same keys in a zoo entry's ``gccp`` map, in ``hierarchy.yml`` and after
``--mask``) and the mask they build (:class:`~sb3_gccp.gccp.mask.GCCPMask` takes one). This module
imports no torch, so that the command line can name the keys without loading it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from gccp_envs.config import (
    IntersectionConfig,
    drop_retired_keys,
    reject_unknown_keys,
    require_int,
    require_non_negative,
    require_positive,
)
from gccp_envs.world import BUILTIN_SIZES, VehicleSizes, vehicle_sizes

if TYPE_CHECKING:
    from torch import nn

    from sb3_gccp.gccp.mask import GCCPMask

PREDICTORS = ("learned", "no_goal", "cv", "none")
"""GCCP variants: the paper's learned predictor, and the ablations w/o goal condition, w/ CV, w/o GCCP."""
LEARNED = ("learned", "no_goal")
"""The variants whose predictor is trained (and saved as ``predictor.pt``)."""
CHECK_PREFIX = "mask_"
"""What a :class:`GCCPCheck` field's name is preceded by in its YAML form."""
VEHICLE_SIZES = ("simulator", "builtin")
"""Whose car sizes the check's boxes have: the simulator's (5 x 2 m in ours, 3.68 x 1.47 m in SMARTS),
or our world's 5 x 2 m in any simulator."""


@dataclass(frozen=True)
class GCCPCheck:
    """How the GCCP mask checks predicted futures for collisions (paper III-C-2, and our additions).

    In YAML every field is named with the prefix ``mask_`` (``mask_margin``, ...): see :meth:`from_dict`.
    """

    margin: float = 0.0
    """Extra length and width [m] of every box in the collision check (paper: none)."""
    extrapolate_steps: int = 0
    """Steps checked beyond the predicted T_f, every vehicle keeping its last predicted velocity
    (paper: 0, a 1 s check; see docs/design.md for why a longer one helps at our speeds)."""
    ego_deceleration: float | None = None
    """In those extra steps the ego brakes to a stop at this deceleration [m/s^2]; null (the shipped
    mask): it goes on at its last predicted velocity like the neighbours. 4 was tried, not adopted."""
    yield_margin: float | None = None
    """A neighbour that stands with the ego's box in its lane ahead waits for the ego: it is checked where
    it stands, with this box margin [m], instead of along its prediction; null: along its prediction
    (the paper). Breaks the stand-offs in which the ego blocks a car that the mask predicts to go."""
    fallback_margin: float | None = None
    """When no candidate passes the check, not even the hold, check them again with this box margin [m]
    (0: the paper's boxes); null: hold. With a margin every candidate can fail beside a standing car that
    waits for the ego, and holding then waits for ever."""
    vehicle_sizes: str = "simulator"
    """The boxes' sizes before the margin: 'simulator', the ego's and the traffic's in the world checked
    (``gccp_envs.world.vehicle_sizes``), or 'builtin', 5 x 2 m for every vehicle, as in our world (what
    the deciders trained in SMARTS before this setting were trained with)."""

    def __post_init__(self) -> None:
        _validate(self.to_dict(), "")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None, where: str = "") -> GCCPCheck:
        """A check from its YAML keys (missing ones keep their defaults).

        :param values: a map of ``CHECK_KEYS`` to values
        :param where: what the messages name the keys by (``"gccp."``, ``"hierarchy.yml: "``)
        :raises ValueError: one line naming an unknown key, or the key whose value is not of its kind
        """
        values = drop_retired_keys(values or {}, RETIRED_CHECK_KEYS, f"{where}GCCP check")
        unknown = sorted(set(values) - set(CHECK_KEYS))
        if unknown:
            expected = ", ".join(CHECK_KEYS)
            raise ValueError(f"unknown GCCP check key(s) {', '.join(unknown)}: expected {expected}")
        _validate(values, where)
        margin, deceleration = values.get("mask_margin", 0.0), values.get("mask_ego_deceleration")
        yield_margin, fallback = values.get("mask_yield_margin"), values.get("mask_fallback_margin")
        return cls(
            float(margin),
            values.get("mask_extrapolate_steps", 0),
            None if deceleration is None else float(deceleration),
            None if yield_margin is None else float(yield_margin),
            None if fallback is None else float(fallback),
            values.get("mask_vehicle_sizes", cls.vehicle_sizes),
        )

    def to_dict(self) -> dict[str, Any]:
        """The YAML form: ``CHECK_KEYS`` to values."""
        return {CHECK_PREFIX + name: value for name, value in asdict(self).items()}

    def replace(self, values: Mapping[str, Any], where: str = "") -> GCCPCheck:
        """This check with the settings of ``values`` (YAML keys) replaced; see :meth:`from_dict`."""
        return GCCPCheck.from_dict({**self.to_dict(), **values}, where)

    def make_mask(self, predictor: nn.Module, world: IntersectionConfig) -> GCCPMask:
        """The GCCP mask function of this check around ``predictor``, for the vehicles of ``world``."""
        from sb3_gccp.gccp.mask import GCCPMask  # the mask module imports this one

        return GCCPMask(predictor, self, self.sizes(world))

    def sizes(self, world: IntersectionConfig) -> VehicleSizes:
        """(length, width) [m] of the ego's box and of the neighbours' before the margin, in ``world``."""
        return vehicle_sizes(world) if self.vehicle_sizes == "simulator" else BUILTIN_SIZES


CHECK_KEYS = tuple(CHECK_PREFIX + f.name for f in dataclasses.fields(GCCPCheck))
"""The YAML keys of a :class:`GCCPCheck`, in order: ``mask_margin``, ``mask_extrapolate_steps``, ..."""
RETIRED_CHECK_KEYS: dict[str, Any] = {
    "mask_standing_escape": False,
    "mask_extrapolate_ego": "straight",
    "mask_unyielded": False,
}
"""Check keys that were tried, not adopted and removed (docs/experiments/), each with the value under which
it changed nothing."""


def _validate(values: Mapping[str, Any], where: str) -> None:
    """Check the YAML form of a :class:`GCCPCheck` (missing keys are fine).

    :raises ValueError: one line naming the key (prefixed ``where``) whose value is not of its kind
    """
    require_non_negative(f"{where}mask_margin", values.get("mask_margin", 0.0))
    require_int(f"{where}mask_extrapolate_steps", values.get("mask_extrapolate_steps", 0), minimum=0)
    if values.get("mask_ego_deceleration") is not None:
        require_positive(f"{where}mask_ego_deceleration", values["mask_ego_deceleration"])
    for key in ("mask_yield_margin", "mask_fallback_margin"):
        if values.get(key) is not None:
            require_non_negative(f"{where}{key}", values[key])
    sizes = values.get("mask_vehicle_sizes", GCCPCheck.vehicle_sizes)
    if sizes not in VEHICLE_SIZES:
        expected = ", ".join(VEHICLE_SIZES)
        raise ValueError(f"{where}mask_vehicle_sizes must be one of {expected}, got {sizes!r}")


@dataclass(frozen=True)
class GCCPSettings:
    """The ``gccp`` map of a decider's zoo config: the paper's schedule, the predictor's training and
    the collision check (its ``mask_*`` keys, see :class:`GCCPCheck`)."""

    n_episodes: int = 2000
    """N_e: decider training episodes (paper: 2000)."""
    mask_after_episodes: int = 800
    """N_m: episodes before the GCCP masks are switched on (paper: 800)."""
    planner_episodes: int | None = None
    """N_g: with ``train --stage all``, stop the planner stage after this many planner-env episodes
    (paper: 500); None trains it for its own ``n_timesteps``."""
    predictor: str = "learned"
    """learned (the paper), no_goal (w/o goal condition), cv (w/ CV) or none (w/o GCCP)."""
    predictor_kwargs: Mapping[str, Any] = field(default_factory=dict)
    """:class:`~sb3_gccp.gccp.predictor.PredictorConfig` fields (encoder sizes, decoder width)."""
    predictor_init: str | None = None
    """Start from these predictor weights (a ``predictor.pt``) instead of random ones."""
    predictor_learning_rate: float = 1e-4
    """Adam's learning rate of the predictor (paper: 1e-4)."""
    predictor_batch_size: int = 64
    """N_b: decisions per predictor gradient step (paper: 64)."""
    predictor_steps_per_episode: int = 5
    """K_p: predictor gradient steps per finished episode (paper: 5)."""
    buffer_capacity: int = 20_000
    """Decisions kept in the replay buffer D (paper: not given)."""
    save_every_episodes: int = 100
    """Episodes between checkpoints (model, predictor, optimiser, replay buffer)."""
    choose_on_flows: int | None = None
    """Ours (the paper keeps the last model): the first traffic seed of the validation flows on which the
    run's candidates (the model every ``choose_every_episodes`` from ``choose_from_episodes`` on, with its
    predictor, and the final one) are evaluated after training, as SB3's ``EvalCallback`` keeps its best
    model; the run's model is the candidate with the highest success there (then fewer collisions, then the
    later). None: the final model."""
    choose_episodes_per_task: int = 100
    """Validation flows per task of each candidate."""
    choose_every_episodes: int = 200
    """Episodes between two candidates."""
    choose_from_episodes: int = 1000
    """The first candidate: the model at the first rollout after this many episodes."""
    check: GCCPCheck = field(default_factory=GCCPCheck)
    """The collision check of the masks, given in the map by its ``mask_*`` keys."""

    def __post_init__(self) -> None:
        from sb3_gccp.gccp.predictor import PredictorConfig  # torch: only once settings are made

        if self.predictor not in PREDICTORS:
            raise ValueError(f"gccp.predictor must be one of {', '.join(PREDICTORS)}, got {self.predictor!r}")
        for name in (
            "n_episodes",
            "predictor_batch_size",
            "buffer_capacity",
            "save_every_episodes",
            "choose_episodes_per_task",
            "choose_every_episodes",
        ):
            require_int(f"gccp.{name}", getattr(self, name))
        for name in ("mask_after_episodes", "predictor_steps_per_episode", "choose_from_episodes"):
            require_int(f"gccp.{name}", getattr(self, name), minimum=0)
        if self.planner_episodes is not None and (
            not isinstance(self.planner_episodes, int) or self.planner_episodes < 1
        ):
            raise ValueError(
                f"gccp.planner_episodes must be a positive integer or null, got {self.planner_episodes!r}"
            )
        if self.choose_on_flows is not None:
            require_int("gccp.choose_on_flows", self.choose_on_flows, minimum=0)
        require_positive("gccp.predictor_learning_rate", self.predictor_learning_rate)
        PredictorConfig.from_dict(self.predictor_kwargs)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> GCCPSettings:
        """Settings from the ``gccp`` map, rejecting unknown keys by name."""
        values = drop_retired_keys(values or {}, RETIRED_CHECK_KEYS, "gccp settings")
        known = [f.name for f in dataclasses.fields(cls) if f.name != "check"] + list(CHECK_KEYS)
        reject_unknown_keys(values, cls, "gccp settings", known)
        check = {key: values.pop(key) for key in CHECK_KEYS if key in values}
        return cls(**values, check=GCCPCheck.from_dict(check, "gccp."))

    def to_dict(self) -> dict[str, Any]:
        """The ``gccp`` map: plain data for YAML, the check's keys last."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "check"}
        values["predictor_kwargs"] = dict(self.predictor_kwargs)
        return {**values, **self.check.to_dict()}

    def make_predictor(self) -> nn.Module | None:
        """A fresh predictor of this variant (``None`` without GCCP)."""
        from sb3_gccp.gccp.predictor import (
            ConstantVelocityPredictor,
            PredictorConfig,
            TrajectoryPredictor,
            load_predictor,
        )

        if self.predictor == "none":
            return None
        if self.predictor == "cv":
            return ConstantVelocityPredictor()
        if self.predictor_init is not None:
            predictor = load_predictor(self.predictor_init)
            if predictor.config.goal_condition != (self.predictor == "learned"):
                raise ValueError(
                    f"gccp.predictor_init {self.predictor_init} is not a {self.predictor} predictor"
                )
            return predictor
        config = PredictorConfig.from_dict(
            {**self.predictor_kwargs, "goal_condition": self.predictor == "learned"}
        )
        return TrajectoryPredictor(config)
