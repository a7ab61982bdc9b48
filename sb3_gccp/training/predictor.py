"""The predictor stage: collect decisions with a frozen planner, train the predictor, report ADE/FDE.

Run folder::

    <log_folder>/predictor/GCCPDecider-v0_<seed>_<time>/
        args.yml, command.txt   the request
        buffer.npz              training decisions (EpisodeReplayBuffer)
        heldout.npz             held-out decisions (other traffic seeds)
        predictor.pt            the goal-conditioned predictor (load_predictor)
        predictor_no_goal.pt    the "w/o goal condition" ablation
        metrics.json            ADE/FDE at 1 s of learned, no-goal and CV on the held-out buffer
        curves.csv              held-out ADE/FDE during training
        fig7.png                ADE/FDE vs gradient steps (paper Fig. 7)
        fig8.png                one scene, two subgoals, predicted trajectories (paper Fig. 8)
"""

from __future__ import annotations

import csv
import json
import shlex
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from torch import nn

from gccp_envs.config import DT, IntersectionConfig, require_int
from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.scripted import FarthestSubgoalDecider
from sb3_gccp.constants import ARGS_FILE, COMMAND_FILE, DECIDER_ENV_ID, METRICS_FILE, PREDICTOR_FILE, SCRIPTED
from sb3_gccp.frozen import FrozenPolicy, load_decider, load_planner
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import (
    ConstantVelocityPredictor,
    PredictorConfig,
    TrajectoryPredictor,
    save_predictor,
)
from sb3_gccp.gccp.replay import EpisodeReplayBuffer, collect_decisions
from sb3_gccp.gccp.settings import GCCPCheck
from sb3_gccp.gccp.training import PredictorTrainer, displacement_errors
from sb3_gccp.progress import new_bar

HELDOUT_SEED_OFFSET = 1_000_000
"""Held-out episodes draw their traffic seeds from ``seed + HELDOUT_SEED_OFFSET``."""
SCENE_EPISODES = 20
"""Episodes searched for each scene of Fig. 8."""


@dataclass
class PredictorRequest:
    """What the user asked of the predictor stage."""

    planner: Path | None = None
    """Frozen motion-planner ``.zip`` that drives the ego while decisions are collected, or
    ``scripted`` (the scripted pure-pursuit planner of ``gccp_envs.scripted``)."""
    buffer: Path | None = None
    """A saved replay buffer to train on instead of collecting (its last ``heldout_share`` is held out)."""
    subgoals: str = "random"
    """How subgoals are chosen while collecting: 'random', 'farthest', or a decider ``.zip``."""
    episodes: int = 200
    heldout_episodes: int = 50
    heldout_share: float = 0.2
    gradient_steps: int = 3000
    eval_every: int = 250
    batch_size: int = 64
    learning_rate: float = 1e-4
    seed: int = 0
    log_folder: Path = Path("runs")
    progress_bar: bool = True
    torch_threads: int | None = None
    world: dict[str, Any] = field(default_factory=dict)
    predictor_kwargs: dict[str, Any] = field(default_factory=dict)
    """:class:`~sb3_gccp.gccp.predictor.PredictorConfig` fields of both learned predictors (but
    ``goal_condition``, which tells them apart)."""
    argv: list[str] = field(default_factory=lambda: list(sys.argv))


def frozen_planner(planner: Path | None, world: IntersectionConfig) -> FrozenPolicy | None:
    """The option env's planner on ``world``: a frozen ``.zip``, or None (the scripted planner) for
    ``scripted``/None."""
    if planner is None or str(planner) == SCRIPTED:
        return None
    return load_planner(planner, world)


Chooser = Callable[[dict[str, np.ndarray], np.ndarray], int]
"""A subgoal policy while decisions are collected: (observation, mask) -> subgoal index."""


def subgoal_chooser(spec: str, rng: np.random.Generator, world: IntersectionConfig) -> Chooser:
    """The subgoal policy named by ``spec``: 'random' (uniform over allowed), 'farthest' or a decider
    ``.zip`` (sampling its policy on ``world``)."""
    if spec == "random":
        return lambda obs, mask: int(rng.choice(np.flatnonzero(mask)))
    if spec == "farthest":
        return FarthestSubgoalDecider()
    return load_decider(spec, world, deterministic=False)


def train_predictor_stage(request: PredictorRequest) -> Path:
    """Run the predictor stage; return the run folder (see the module docstring)."""
    if request.torch_threads is not None:
        require_int("--torch-threads", request.torch_threads)
        th.set_num_threads(request.torch_threads)
    if request.planner is None and request.buffer is None:
        raise ValueError("give --planner (to collect decisions) or --buffer (a saved replay buffer)")
    for name in ("planner", "buffer"):
        path = getattr(request, name)
        if path is not None and str(path) != SCRIPTED and not Path(path).is_file():
            raise ValueError(f"--{name}: no such file: {path}")
    if request.gradient_steps < 1 or request.eval_every < 1 or request.episodes < 1:
        raise ValueError("--gradient-steps, --eval-every and --episodes must be positive")
    if request.heldout_episodes < 0:
        raise ValueError(f"--heldout-episodes must be 0 or more, got {request.heldout_episodes}")
    if request.subgoals not in ("random", "farthest") and not Path(request.subgoals).is_file():
        raise ValueError(
            f"--subgoals must be 'random', 'farthest' or a decider .zip; no file {request.subgoals}"
        )
    world = IntersectionConfig.from_dict(request.world)
    if "goal_condition" in request.predictor_kwargs:
        raise ValueError("--predictor-set goal_condition: the stage trains both (learned and no_goal)")
    PredictorConfig.from_dict(request.predictor_kwargs)
    rng = np.random.default_rng(request.seed)
    # The models and the buffer are loaded before the run folder is made: one that does not fit fails here.
    collector, given = None, None
    if request.buffer is None:
        collector = frozen_planner(request.planner, world), subgoal_chooser(request.subgoals, rng, world)
    else:
        given = _split(EpisodeReplayBuffer.load(request.buffer), request.heldout_share)
    run_dir = (
        request.log_folder / "predictor" / f"{DECIDER_ENV_ID}_{request.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    )
    run_dir.mkdir(parents=True, exist_ok=False)
    (run_dir / COMMAND_FILE).write_text(shlex.join(request.argv) + "\n")
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(request).items() if k != "argv"}
    (run_dir / ARGS_FILE).write_text(yaml.safe_dump(args, sort_keys=False))

    th.manual_seed(request.seed)
    train, heldout = given or _collect(request, world, rng, collector)
    train.save(run_dir / "buffer.npz")
    heldout.save(run_dir / "heldout.npz")
    print(f"decisions: {len(train)} for training, {len(heldout)} held out")

    predictors: dict[str, nn.Module] = {}
    curves: list[dict[str, float]] = []
    for name, goal_condition in (("learned", True), ("no_goal", False)):
        config = PredictorConfig.from_dict({**request.predictor_kwargs, "goal_condition": goal_condition})
        predictor = TrajectoryPredictor(config)
        trainer = PredictorTrainer(predictor, request.learning_rate, request.batch_size)
        steps = new_bar(
            range(0, request.gradient_steps, request.eval_every),
            enabled=request.progress_bar,
            desc=f"training {name}",
        )
        for start in steps:
            n = min(request.eval_every, request.gradient_steps - start)
            loss = trainer.train_steps(train, n, rng)
            errors = displacement_errors(predictor, heldout)
            curves.append({"predictor": name, "step": start + n, "loss": loss, **errors})  # type: ignore[dict-item]
        save_predictor(predictor, run_dir / (PREDICTOR_FILE if goal_condition else "predictor_no_goal.pt"))
        predictors[name] = predictor
    predictors["cv"] = ConstantVelocityPredictor()
    metrics = {name: displacement_errors(p, heldout) for name, p in predictors.items()}
    (run_dir / METRICS_FILE).write_text(json.dumps(metrics, indent=2))
    with open(run_dir / "curves.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(curves[0]))
        writer.writeheader()
        writer.writerows(curves)
    print(format_errors(metrics))
    plot_errors(curves, metrics["cv"], run_dir / "fig7.png")
    plot_scene(predictors["learned"], world, request.seed, run_dir / "fig8.png", request.planner)
    return run_dir


def _split(
    loaded: EpisodeReplayBuffer, heldout_share: float
) -> tuple[EpisodeReplayBuffer, EpisodeReplayBuffer]:
    """A loaded buffer's decisions for training and held out, the last ``heldout_share`` held out."""
    arrays = loaded.stored()
    split = round(len(loaded) * (1 - heldout_share))
    if not 0 < split < len(loaded):
        raise ValueError(f"--buffer holds {len(loaded)} decisions: too few to hold some out")
    return _buffer_of(arrays, slice(0, split)), _buffer_of(arrays, slice(split, None))


def _collect(
    request: PredictorRequest,
    world: IntersectionConfig,
    rng: np.random.Generator,
    collector: tuple[FrozenPolicy | None, Chooser] | None,
) -> tuple[EpisodeReplayBuffer, EpisodeReplayBuffer]:
    """Training and held-out decisions collected on disjoint traffic seeds by ``collector`` (the planner
    and the subgoal policy)."""
    assert collector is not None
    planner, choose = collector
    env = GCCPDeciderEnv(config=world, planner=planner)
    per_episode = int(np.ceil(world.duration / (world.decision_period * DT))) + 1
    train = EpisodeReplayBuffer(capacity=request.episodes * per_episode)
    heldout = EpisodeReplayBuffer(capacity=max(request.heldout_episodes, 1) * per_episode)
    collect_decisions(env, choose, request.episodes, train, rng, progress=request.progress_bar)
    held_rng = np.random.default_rng(request.seed + HELDOUT_SEED_OFFSET)
    collect_decisions(env, choose, request.heldout_episodes, heldout, held_rng, progress=request.progress_bar)
    return train, heldout


def _buffer_of(arrays: Mapping[str, np.ndarray], rows: slice) -> EpisodeReplayBuffer:
    """A replay buffer holding ``rows`` of stored decision arrays."""
    part = {key: value[rows] for key, value in arrays.items()}
    buffer = EpisodeReplayBuffer(capacity=len(part["future"]))
    for i in range(len(part["future"])):
        buffer.add(
            {key: part[key][i] for key in part},
            part["subgoal"][i],
            part["future"][i],
            part["future_mask"][i],
        )
    buffer.end_episode()
    return buffer


def format_errors(metrics: Mapping[str, Mapping[str, float]]) -> str:
    """A markdown table of ADE/FDE at 1 s per predictor."""
    names = {"learned": "goal-conditioned (ours)", "no_goal": "w/o goal condition", "cv": "constant velocity"}
    lines = [
        "| predictor | ADE [m] | FDE [m] | ego ADE | ego FDE | neighbour ADE | neighbour FDE |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, m in metrics.items():
        cells = [m[k] for k in ("ade", "fde", "ego_ade", "ego_fde", "neighbour_ade", "neighbour_fde")]
        lines.append(f"| {names.get(key, key)} | " + " | ".join(f"{c:.3f}" for c in cells) + " |")
    return "\n".join(lines)


def plot_errors(curves: list[dict[str, Any]], cv: Mapping[str, float], path: Path) -> None:
    """ADE and FDE on the held-out buffer vs gradient steps, learned vs no-goal, CV as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for ax, metric in zip(axes, ("ade", "fde"), strict=True):
        for name, label in (("learned", "goal-conditioned"), ("no_goal", "w/o goal condition")):
            rows = [c for c in curves if c["predictor"] == name]
            ax.plot([r["step"] for r in rows], [r[metric] for r in rows], label=label)
        ax.axhline(cv[metric], color="grey", linestyle="--", label="constant velocity")
        ax.set_xlabel("gradient steps")
        ax.set_ylabel(f"{metric.upper()} at 1 s [m]")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_scene(
    predictor: nn.Module,
    world: IntersectionConfig,
    seed: int,
    path: Path,
    planner: Path | None,
    tasks: Sequence[str | None] = (None,),
    decider: Callable[[dict[str, np.ndarray], np.ndarray], int] | None = None,
) -> None:
    """Paper Fig. 8: scenes with neighbours, the predicted futures under two subgoals each.

    Scene i is searched in the episodes from seed ``seed + SCENE_EPISODES i`` on: the first decision
    with at least two neighbours in view of which GCCP masks a subgoal (shown next to an allowed one),
    else the first with two neighbours in view (its nearest and farthest subgoal), else the last one.

    :param tasks: one scene (a row of the figure) per entry: the task of its episode, None for the
        world's own task draw
    :param decider: drives the episodes (subgoal from observation and mask) so that later decisions are
        searched too; None searches the first decision of each episode only
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = GCCPDeciderEnv(config=world, planner=frozen_planner(planner, world))
    gccp = GCCPCheck().make_mask(predictor, world)
    fig, axes = plt.subplots(len(tasks), 2, figsize=(10, 5 * len(tasks)), squeeze=False)
    for i, (row, task) in enumerate(zip(axes, tasks, strict=True)):
        obs = _busy_scene(env, gccp, seed + SCENE_EPISODES * i, task, world.bev_extent / 2, decider)
        _draw_scene(row, obs, gccp, world, "" if task is None else f"{task}: ")
    fig.suptitle("Goal-conditioned predictions: ego (green), neighbours (orange), 1 s at 0.1 s")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _busy_scene(
    env: GCCPDeciderEnv,
    gccp: GCCPMask,
    seed: int,
    task: str | None,
    extent: float,
    decider: Callable[[dict[str, np.ndarray], np.ndarray], int] | None,
) -> dict[str, np.ndarray]:
    """A decision to draw (see :func:`plot_scene`)."""
    obs: dict[str, np.ndarray] = {}
    busy: dict[str, np.ndarray] | None = None
    for k in range(SCENE_EPISODES):
        obs, _ = env.reset(seed=seed + k, options=None if task is None else {"task": task})
        while True:
            present = obs["history_mask"][1:].any(-1)
            near = np.abs(obs["history"][1:, -1, 4:6]).max(-1) <= extent
            if (present & near).sum() >= 2:
                if not gccp(obs).all():
                    return obs
                busy = obs if busy is None else busy
            if decider is None:
                break
            obs, _, terminated, truncated, _ = env.step(decider(obs, env.action_masks()))
            if terminated or truncated:
                break
    return obs if busy is None else busy


def _draw_scene(
    axes: Any, obs: dict[str, np.ndarray], gccp: GCCPMask, world: IntersectionConfig, title: str
) -> None:
    """One scene in two panels: the predicted futures under two subgoals."""
    future = gccp.predict(obs)
    allowed = gccp(obs)
    subgoals = obs["subgoals"]
    ahead = subgoals[:, 0]
    if allowed.all() or not allowed.any():
        pair = (int(np.argmin(ahead)), int(np.argmax(ahead)))
    else:  # the farthest allowed and the farthest masked subgoal
        pair = (
            int(np.argmax(np.where(allowed, ahead, -np.inf))),
            int(np.argmax(np.where(allowed, -np.inf, ahead))),
        )
    extent = world.bev_extent / 2
    for ax, index in zip(axes, pair, strict=True):
        ax.imshow(obs["bev"][0], cmap="Greys", vmin=-1, vmax=2, extent=(-extent, extent, -extent, extent))
        present = obs["history_mask"].any(-1)
        for v in np.flatnonzero(present):
            x, y, heading = (0.0, 0.0, 0.0) if v == 0 else obs["history"][v, -1, 4:7]
            _draw_box(ax, x, y, heading, "tab:green" if v == 0 else "tab:blue")
            track = future[index, v]
            ax.plot(track[:, 1], track[:, 0], ".-", color="tab:green" if v == 0 else "tab:orange", ms=3)
        ax.plot(subgoals[:, 1], subgoals[:, 0], "o", color="tab:blue", ms=4, alpha=0.4)
        ax.plot(subgoals[index, 1], subgoals[index, 0], "*", color="gold", ms=14, mec="black")
        verdict = "safe" if allowed[index] else "masked: predicted collision"
        ax.set_title(f"{title}subgoal {index} ({subgoals[index, 0]:.1f} m ahead): {verdict}", fontsize=9)
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_xlabel("right of ego [m]")
        ax.set_ylabel("ahead of ego [m]")


def _draw_box(ax: Any, x: float, y: float, heading: float, color: str) -> None:
    """A 5 m x 2 m vehicle box in the (right, ahead) plot axes."""
    from matplotlib.patches import Polygon

    from gccp_envs.geometry import box_corners

    corners = box_corners(x, y, heading, 5.0, 2.0)
    ax.add_patch(Polygon(corners[:, ::-1], closed=True, color=color, alpha=0.8))
