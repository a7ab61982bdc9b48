"""One typed source of truth for every constant of the intersection world.

Paper references are to Huang, "Goal-conditioned Hierarchical Reinforcement Learning for
Sample-efficient and Safe Autonomous Driving at Intersections" (section numbers of the LaTeX source).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, fields
from typing import Any

from gccp_envs.smarts import require_smarts_extra
from gccp_envs.sumo import require_sumo_extra

TASKS = ("left", "straight", "right")
"""The paper's three scenarios: turning left, going straight, turning right."""

DT = 0.1
"""Seconds per policy step and per simulation step: the paper's actions are reached in 0.1 s."""

TRAFFIC_BACKENDS = ("builtin", "sumo")
"""Who drives the other vehicles (config ``traffic``)."""
SIMULATORS = ("builtin", "smarts")
"""Who simulates the world (config ``simulator``)."""
SMARTS_ROUTES = ("layout", "waypoints")
"""Who chooses the ego's routes under SMARTS (config ``smarts_routes``)."""


def parse_tasks(text: str) -> list[str]:
    """Comma-separated task names (``left,right``), validated.

    :raises ValueError: one line naming the unknown tasks
    """
    tasks = [t.strip() for t in text.split(",") if t.strip()]
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise ValueError(
            f"unknown task(s) {', '.join(map(repr, unknown)) or '(none)'}: expected a "
            f"comma-separated subset of {','.join(TASKS)}"
        )
    return tasks


def reject_unknown_keys(
    values: Mapping[str, Any], config_class: type, what: str, known: Collection[str] | None = None
) -> None:
    """Raise ``ValueError`` naming every key of ``values`` that is not a field of ``config_class``.

    :param values: candidate field values (for example a YAML map)
    :param config_class: a dataclass
    :param what: what the keys configure, for the message ("intersection config")
    :param known: the keys its YAML form takes, when they are not its field names
    :raises ValueError: one line listing the unknown keys, each with its closest field name if any
    """
    known = {f.name for f in fields(config_class)} if known is None else set(known)
    not_names = [key for key in values if not isinstance(key, str)]
    if not_names:
        raise ValueError(f"{what} keys are names, got {', '.join(repr(key) for key in not_names)}")
    unknown = sorted(set(values) - known)
    if unknown:
        hints = [
            (
                f"{key!r} (did you mean {close[0]!r}?)"
                if (close := difflib.get_close_matches(key, known, 1))
                else repr(key)
            )
            for key in unknown
        ]
        raise ValueError(f"unknown {what} key(s): {', '.join(hints)}")


def drop_retired_keys(values: Mapping[str, Any], retired: Mapping[str, Any], what: str) -> dict[str, Any]:
    """``values`` without the keys that earlier versions wrote and this one no longer has, so that run
    folders written then still load; each such key must hold the value under which it changed nothing.

    :param values: candidate field values (for example a YAML map)
    :param retired: each removed key with the value under which it changed nothing
    :param what: what the keys configure, for the message ("intersection config")
    :raises ValueError: one line naming a removed key that holds another value
    """
    kept = dict(values)
    for key, neutral in retired.items():
        if key in kept and (value := kept.pop(key)) != neutral:
            raise ValueError(
                f"{what} key {key!r} was removed; a run that set it to {value!r} cannot load "
                f"(only {neutral!r}, its value that changed nothing)"
            )
    return kept


RETIRED_WORLD_KEYS: dict[str, Any] = {"r_fail": 0.0, "r_junction_stand": 0.0, "lane_change_distance": 0.0}
"""World keys of the decider's world that were tried, not adopted and removed (docs/experiments/), each with
the value under which it changed nothing."""


def require_int(name: str, value: Any, minimum: int = 1) -> None:
    """Raise ``ValueError`` unless ``value`` is an integer (not a bool) of at least ``minimum`` (0 or 1).

    :param name: the key as the user wrote it, for the message ("gccp.n_episodes")
    """
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        kind = "a positive" if minimum >= 1 else "a non-negative"
        raise ValueError(f"{name} must be {kind} integer, got {value!r}")


def require_positive(name: str, value: Any) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number (not a bool) above zero."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 < value < math.inf:
        raise ValueError(f"{name} must be a positive number, got {value!r}")


def require_non_negative(name: str, value: Any) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number (not a bool) of at least zero."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < math.inf:
        raise ValueError(f"{name} must be a non-negative number, got {value!r}")


def require_in_range(name: str, value: Any, low: float, high: float, unit: str = "") -> None:
    """Raise ``ValueError`` unless ``value`` is a number (not a bool) in ``[low, high]``.

    :param unit: said after the range in the message (" m (0: off)")
    """
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not low <= value <= high:
        raise ValueError(f"{name} must be in [{low:g}, {high:g}]{unit}, got {value!r}")


@dataclass(frozen=True)
class IntersectionConfig:
    """Configuration of the intersection world shared by the planner, decider and flat envs.

    Every field has the paper's value where the paper sets one; the others are our choices, documented
    in the README ("Design choices").
    """

    # --- scenario --------------------------------------------------------------------------------
    task: str = "mixed"
    """'left' | 'straight' | 'right', or 'mixed' to draw one per episode (paper IV: trained together)."""
    lanes_per_approach: int = 2
    """Lanes per direction on every arm; 1 is highway-env's single-lane layout (paper Fig. 8 C: 2)."""
    lane_width: float = 4.0
    """Lane width [m] (highway-env's default)."""
    corner_radius: float = 5.0
    """Radius [m] of the kerb at the four corners of the junction box."""
    approach_length: float = 70.0
    """Length [m] of every arm, from the junction box to where traffic appears or leaves."""
    duration: float = 30.0
    """Episode time limit [s]; reaching it truncates the episode."""
    ego_start_distance: tuple[float, float] = (25.0, 40.0)
    """Range [m] of the ego's start distance before its stop line, drawn uniformly."""
    ego_start_speed: tuple[float, float] = (4.0, 8.0)
    """Range [m/s] of the ego's start speed, drawn uniformly."""
    ego_start_standing: float = 0.0
    """Chance that the ego instead starts at rest at a uniform point of one of its task's paths, from
    10 m before the stop line to 5 m past the junction box (ours, for the planner env: a decision-maker
    can stop the car anywhere, also inside a turn, and the planner must drive off from there)."""
    ego_lane: str = "random"
    """'random': ego starts on any lane of its arm (it may need a lane change); 'task': a task lane."""
    exit_distance: float = 20.0
    """Distance [m] past the junction box on the task's exit arm that counts as task success."""

    # --- simulator -------------------------------------------------------------------------------
    simulator: str = "builtin"
    """Who simulates the world: 'builtin', ours (envs/world.py), or 'smarts', the paper's simulator (paper
    IV) on the same junction, with SUMO's traffic, the ego moved by its RelativeTargetPose action and the
    outcomes from its events (envs/smarts/, the ``smarts`` extra). With 'smarts' the key ``traffic`` is
    not read: SMARTS's traffic is SUMO's, with the flow rates and speeds of the keys below."""
    smarts_flows: int = 50
    """Traffic variations per task scenario under SMARTS, one drawn per episode (paper IV: 50 flows)."""
    smarts_grid_map: bool = True
    """Under SMARTS, the bird's-eye view is SMARTS's drivable-area grid map (its camera sensor, as the paper's
    state), not drawn from our layout of the same map (they agree on about 99 % of the cells); false saves
    SMARTS's rendering."""
    smarts_clear_start: bool = True
    """Under SMARTS, SUMO's vehicles within 15 m of the ego when it enters are taken off the road, as our
    world and SUMO's traffic (``traffic: sumo``) start an episode; false keeps SMARTS's start as it comes,
    with cars beside or behind an ego that appears among them at speed."""
    smarts_routes: str = "layout"
    """Under SMARTS, which lane paths are the ego's routes: 'layout', our rule (every path of the task before
    the stop line, the paths within a lane width after it), or 'waypoints', those SMARTS's waypoint paths
    along the ego's mission run on (the paper's routes; inside the junction they also keep the task's
    other lanes). The route points come from our layout either way: SMARTS's map is that layout."""

    # --- traffic ---------------------------------------------------------------------------------
    traffic: str = "builtin"
    """Who drives the other vehicles: 'builtin', our IDM drivers and commit protocol (envs/traffic.py), or
    'sumo', SUMO's own drivers, junction model and gap acceptance on the same junction (envs/sumo/, the
    ``sumo`` extra; the paper's SMARTS runs SUMO). The keys below set both, except ``npc_patience``."""
    spawn_probability: float = 0.06
    """Chance per 0.1 s step of one spawn attempt on a random inbound lane (highway-env semantics;
    0.06 at 10 Hz matches the density of intersection-v0 at its default 1 Hz)."""
    warmup_time: float = 12.0
    """Seconds of traffic simulated before the ego appears, so the junction is populated."""
    npc_speed_range: tuple[float, float] = (7.0, 10.0)
    """Desired speeds [m/s] of other vehicles, drawn uniformly per vehicle."""
    npc_time_headway: tuple[float, float] = (1.0, 1.6)
    """Time headways [s] of other vehicles (IDM's T; SUMO's tau), drawn uniformly per vehicle."""
    npc_patience: float | None = 8.0
    """Seconds another vehicle stands at its stop line before it goes before all vehicles that have not:
    priority traffic not yet committed stops for it (it can still stop comfortably), committed traffic
    and a standing ego still hold it back. SUMO's impatience, without which a minor-road car can wait for
    a gap past the time limit with the ego queued behind it (ours; null: never impatient). Builtin traffic
    only: SUMO's drivers have SUMO's own impatience."""
    crashed_vehicle_lifetime: float = 3.0
    """Seconds a crashed other vehicle stays on the road before it is removed."""
    max_vehicles: int = 48
    """Capacity of the traffic table; spawns are skipped when it is full."""

    # --- ego motion (paper III-D-2: N_a = 6 pose changes reached in 0.1 s) -------------------------
    cruise_speed: float = 8.0
    """Speed [m/s] that 'keep direction' accelerates back to."""
    acceleration: float = 2.0
    """Acceleration [m/s^2] of 'keep direction' below cruise speed."""
    deceleration: float = 4.0
    """Deceleration [m/s^2] of 'slow down'; the ego stops fully from cruise speed in 2 s."""
    slow_turn_curvature: float = 1.0 / 12.0
    """Curvature [1/m] of 'slowly turn left/right' (a left turn needs 1/15)."""
    quick_turn_curvature: float = 1.0 / 6.0
    """Curvature [1/m] of 'quickly turn left/right' (a right turn needs 1/7)."""
    rear_axle_offset: float = 0.0
    """Distance [m] behind the box's centre of the point the ego turns about, as a car turns about its
    rear axle: that point drives the action's arc and the box follows it. 0 (the default): the box turns
    about its centre, so a turn swings its rear corners out by half its length. 1.5 and 0.75 were tried
    and not adopted (docs/experiments/2026-11-28-ego-turning-about-its-rear-axle.md)."""
    scripted_stop_aligned: bool = False
    """Whether the scripted planner, stopping on a goal whose heading differs from its own, first turns
    towards it (a turn holds speed, so it brakes a step later) rather than braking askew across lanes.
    Tried and not adopted: fewer stand-offs, more collisions
    (docs/experiments/2026-11-25-stand-offs-at-the-stop-line.md)."""
    scripted_turn_speed: float = 1.0
    """Speed [m/s] up to which the scripted planner, going on through a turn, steers with 'keep direction'
    or a quick turn, whichever curvature is nearer pure pursuit's, so that it accelerates on the straight
    steps (a turn holds the speed). Below 1 m/s it always accelerates straight first, so the default 1.0
    adds nothing, and an ego that starts a turn from a stop crawls through it at 1 m/s; the shipped
    hierarchy runs 4.0 (ours; docs/experiments/2026-11-25-turn-speed-and-yield-margin.md)."""
    mask_lookahead: int = 10
    """Steps the action mask looks ahead: an action is allowed if the ego stays on the road after it
    and some action held for the remaining steps keeps it there (1: the next step only). 10 (1 s): at 5
    a planner could still enter a right-hand corner too fast to stay on the road
    (docs/experiments/2026-11-26-collisions-over-the-learned-planner.md)."""
    mask_drive_on: float = 0.0
    """Metres [m] the ego must be able to drive on after an allowed action: the action mask also asks
    that from the pose after it some path of two arcs of the actions' curvatures (one for the first
    0-n metres, another for the rest) keeps the box on the road this far. 0: not asked. It keeps the
    ego out of poses from which every way on leaves the road, such as the end of a right turn taken at
    cruise speed beside the kerb, where no action held for ``mask_lookahead`` steps stays on the road and
    the mask falls back to the next step. 10 was tried and not adopted
    (docs/experiments/2026-11-28-a-mask-that-asks-for-a-way-on.md)."""

    # --- state (paper III-B-1) -------------------------------------------------------------------
    num_neighbours: int = 5
    """N_s: surrounding vehicles in the state, nearest first (paper: 5)."""
    history_length: int = 10
    """T_h: history vectors per vehicle, one per 0.1 s step (paper: not given; 1 s)."""
    num_routes: int = 3
    """N_r: routes per vehicle (paper: 3)."""
    route_points: int = 50
    """N_p: waypoint vectors per route (paper: 50)."""
    route_spacing: float = 1.0
    """Spacing [m] of route waypoints (paper: 1 m)."""
    bev_size: int = 64
    """Pixels per side of the drivable-area bird's-eye view (paper: 64)."""
    bev_extent: float = 50.0
    """Metres covered by the bird's-eye view, centred on the ego (paper: 50 m)."""
    observation_radius: float = 50.0
    """Vehicles farther than this [m] from the ego are not neighbours."""

    # --- subgoals and hierarchy (paper III-B-2, III-D) -------------------------------------------
    num_subgoals: int = 12
    """N: subgoal candidates (paper: 12)."""
    subgoal_spacing: float = 5.0
    """Spacing [m] of subgoal candidates along a route (paper: 5 m)."""
    subgoal_range: float = 20.0
    """Length [m] of the window of candidates along a route (paper: 20 m)."""
    subgoal_reach_radius: float = 2.0
    """A subgoal counts as reached within this distance [m] ..."""
    subgoal_reach_heading: float = 0.5
    """... and this heading difference [rad]."""
    decision_period: int = 10
    """T_m: motion-planner steps per decision (paper: 10)."""
    prediction_horizon: int = 10
    """T_f: future poses predicted per vehicle, at 0.1 s (paper: 10)."""
    fallback_brakes: bool = False
    """Option env: when the mask function allows no candidate, the ego brakes ('slow down', where the
    action mask allows it) until it stands, instead of the planner driving to the nearest candidate, the
    env's fallback. A planner held on a candidate it has already passed brakes for a few steps and then
    steers towards it, and a turn holds the speed, so the ego rolled on into the conflict the check had
    just seen (ours; docs/experiments/2026-11-28-brake-when-nothing-passes.md). Where ``fallback_go_on``
    lets the ego go on instead, it does not brake."""
    fallback_go_on: bool = False
    """Option env: when the mask function allows no candidate while the ego drives (at least 1 m/s) inside
    the junction, allow the candidates whose first predicted collision comes latest (the mask function's
    ``latest_collision``, where it has one) instead of the nearest: held inside the junction, the ego
    brakes to a stand on the crossing paths it was about to clear, where it is hit or stands nose to nose
    with a car waiting for it (ours; docs/experiments/2026-11-29-going-on-inside-the-junction.md)."""
    standing_turn_drives: bool = False
    """Option env: when the ego stands and the planner picks a turn, which cannot move a standing car (a
    turn holds the speed), the ego takes 'keep direction' instead, if its subgoal lies beyond
    ``subgoal_reach_radius`` and the action mask allows it. A frozen planner that stands with its subgoal
    off to the side can pick a turn step after step and stand until the time limit, every candidate
    allowed (ours; not adopted: docs/experiments/2026-12-04-a-turn-from-a-standstill.md)."""
    fallback_go_on_skips_hold: bool = False
    """Option env, with ``fallback_go_on``: the nearest candidate (the hold, 1-2 m ahead) is left out of
    the ranking, so that the ego does not stop on a crossing path because braking there puts its predicted
    collision a step later (ours; not adopted: docs/experiments/2026-11-30-going-on-past-the-hold.md)."""
    observe_mask: bool = False
    """Option env: the decision-maker observes the mask function's verdict on each candidate (1: allowed,
    0: ruled out, before the env's fallback), under the key ``subgoal_allowed``, and its features take it
    beside each candidate, so that its value sees how much the GCCP check leaves open. Off: the mask
    reaches the decision-maker only through its logits (paper III-D says that the decider observes the
    mask, and defines its state without it; a mask function installed mid-episode shows from the next
    observation on; docs/experiments/2026-11-29-the-decider-observes-the-mask.md)."""
    hold_probability: float = 0.05
    """Planner env: chance that a new subgoal is a 'hold' (the candidate nearest the ego), so that the
    planner learns to stop where the decision-maker holds it (paper: not given; 0 = always uniform)."""
    hold_continue: float = 0.9
    """Planner env: chance that a hold subgoal is drawn again at the next redraw (mean hold 10 s)."""
    hold_stop_speed: float = 1.0
    """Planner env: a hold subgoal counts as reached only below this speed [m/s] (the car stands on it)."""

    # --- motion-planner reward (paper Eq. r^m) ---------------------------------------------------
    r_time: float = -0.05
    """Time penalty per step (paper: -0.05)."""
    r_time_hold: float = 0.0
    """Time penalty per step in the planner env while it holds the ego (``hold_probability``): without
    it, rushing to the task exit costs less than waiting on a held point (ours; r_time elsewhere)."""
    r_arr: float = 1.0
    """Reward for reaching the subgoal (paper: 1.0)."""
    r_col: float = -1.0
    """Collision penalty (paper: -1)."""
    r_off: float = -1.0
    """Off-road penalty (paper: -1)."""
    wrong_exit_penalty: bool = True
    """Pay ``r_off`` also when the ego leaves the junction by another exit than its task's, which ends the
    episode as leaving the road does (ours; paper: False, and a flat baseline that leaves by the nearest
    exit loses nothing against one that drives off the road)."""
    eps_d: float = 0.05
    """epsilon_d: weight of the decrease of the distance to the subgoal (paper: 0.05)."""
    eps_h: float = 0.5
    """epsilon_h: weight of the decrease of the heading difference to the subgoal (paper: 0.5)."""

    # --- decision-maker reward (paper Eq. r^d) ---------------------------------------------------
    r_goal: float = 3.0
    """Reward when the task goal is reached (paper: 3)."""
    r_subgoal: float = 0.5
    """Reward when the subgoal is reached within T_m steps (paper: 0.5)."""
    r_subgoal_needs_travel: bool = False
    """Pay r_subgoal only for a subgoal farther than the reach radius when chosen, so that holding the
    ego on the candidate it stands on is not paid (ours; paper: False, and then waiting on our lattice
    costs r_near + r_subgoal = 0 per decision)."""
    r_near: float = -0.5
    """Constant of the subgoal-distance term (paper: -0.5)."""
    eps_s: float = 0.05
    """epsilon_s: weight of the distance to the chosen subgoal (paper: 0.05)."""

    def __post_init__(self) -> None:
        _validate(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None = None, **overrides: Any) -> IntersectionConfig:
        """Build a config from a mapping, rejecting unknown keys with a message naming them.

        :param values: field values (for example a YAML map)
        :param overrides: more field values, taking precedence
        :return: the validated config
        """
        merged = drop_retired_keys({**(values or {}), **overrides}, RETIRED_WORLD_KEYS, "intersection config")
        reject_unknown_keys(merged, cls, "intersection config")
        tuples = {k: tuple(v) for k, v in merged.items() if isinstance(v, list)}
        return cls(**{**merged, **tuples})

    def replace(self, **changes: Any) -> IntersectionConfig:
        """Return a copy with some fields changed (validated like :meth:`from_dict`).

        :param changes: new field values
        :return: the new config
        """
        return type(self).from_dict({**dataclasses.asdict(self), **changes})

    @property
    def road_half_width(self) -> float:
        """Half width [m] of a road: all lanes of one direction."""
        return self.lanes_per_approach * self.lane_width

    @property
    def junction_half_size(self) -> float:
        """Distance [m] from the centre to every stop line (the junction box's half size)."""
        return self.road_half_width + self.corner_radius


def _validate(config: IntersectionConfig) -> None:
    """Raise ``ValueError`` naming the first bad field."""
    for field in fields(config):
        value = getattr(config, field.name)
        if any(
            isinstance(v, float) and not math.isfinite(v)
            for v in (value if isinstance(value, tuple) else (value,))
        ):
            raise ValueError(f"{field.name} must be finite, got {value!r}")
        if field.type == "float" and (not isinstance(value, (int, float)) or isinstance(value, bool)):
            raise ValueError(f"{field.name} must be a number, got {value!r}")
    if config.task not in (*TASKS, "mixed"):
        raise ValueError(f"unknown task {config.task!r}: expected one of {', '.join((*TASKS, 'mixed'))}")
    if config.traffic not in TRAFFIC_BACKENDS:
        raise ValueError(f"unknown traffic {config.traffic!r}: expected one of {', '.join(TRAFFIC_BACKENDS)}")
    if config.traffic == "sumo":
        require_sumo_extra()
    if config.simulator not in SIMULATORS:
        raise ValueError(f"unknown simulator {config.simulator!r}: expected one of {', '.join(SIMULATORS)}")
    if config.simulator == "smarts":
        require_smarts_extra()
    if config.smarts_routes not in SMARTS_ROUTES:
        raise ValueError(
            f"unknown smarts_routes {config.smarts_routes!r}: expected one of {', '.join(SMARTS_ROUTES)}"
        )
    if config.ego_lane not in ("random", "task"):
        raise ValueError(f"ego_lane must be 'random' or 'task', got {config.ego_lane!r}")
    positive_ints = (
        "lanes_per_approach",
        "num_neighbours",
        "history_length",
        "num_routes",
        "route_points",
        "bev_size",
        "num_subgoals",
        "decision_period",
        "prediction_horizon",
        "max_vehicles",
        "mask_lookahead",
        "smarts_flows",
    )
    for name in positive_ints:
        require_int(name, getattr(config, name))
    positive_floats = (
        "lane_width",
        "corner_radius",
        "approach_length",
        "duration",
        "exit_distance",
        "cruise_speed",
        "acceleration",
        "deceleration",
        "slow_turn_curvature",
        "quick_turn_curvature",
        "route_spacing",
        "bev_extent",
        "observation_radius",
        "subgoal_spacing",
        "subgoal_range",
        "subgoal_reach_radius",
        "subgoal_reach_heading",
        "hold_stop_speed",
        "scripted_turn_speed",
    )
    for name in positive_floats:
        require_positive(name, getattr(config, name))
    if config.npc_patience is not None:
        require_positive("npc_patience", config.npc_patience)
    for name in (
        "scripted_stop_aligned",
        "fallback_brakes",
        "fallback_go_on",
        "fallback_go_on_skips_hold",
        "standing_turn_drives",
        "observe_mask",
        "r_subgoal_needs_travel",
        "smarts_grid_map",
        "smarts_clear_start",
        "wrong_exit_penalty",
    ):
        if not isinstance(getattr(config, name), bool):
            raise ValueError(f"{name} must be true or false, got {getattr(config, name)!r}")
    for name in ("spawn_probability", "hold_probability", "hold_continue", "ego_start_standing"):
        require_in_range(name, getattr(config, name), 0.0, 1.0)
    for name in ("ego_start_distance", "ego_start_speed", "npc_speed_range", "npc_time_headway"):
        low_high = getattr(config, name)
        numbers = isinstance(low_high, (list, tuple)) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in low_high
        )
        if not numbers or len(low_high) != 2 or not 0 <= low_high[0] <= low_high[1]:
            raise ValueError(f"{name} must be a (low, high) pair with 0 <= low <= high, got {low_high!r}")
    if config.ego_start_distance[1] > config.approach_length - 10.0:
        raise ValueError("ego_start_distance must leave at least 10 m of approach behind the ego")
    if config.exit_distance > config.approach_length - 10.0:
        raise ValueError("exit_distance must be at least 10 m shorter than approach_length")
    if config.prediction_horizon > config.decision_period:
        raise ValueError("prediction_horizon (T_f) must not exceed decision_period (T_m)")
    require_in_range("mask_drive_on", config.mask_drive_on, 0.0, 30.0, " m (0: off)")
    require_in_range("rear_axle_offset", config.rear_axle_offset, 0.0, 2.5, " m (the box's rear half)")
    if config.quick_turn_curvature < config.slow_turn_curvature:
        raise ValueError("quick_turn_curvature must be at least slow_turn_curvature")
