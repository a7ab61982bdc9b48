"""The decision-maker stage: MaskablePPO on ``GCCPDecider-v0`` with the frozen planner and GCCP.

Run folder (``<log_folder>/decider/GCCPDecider-v0_<seed>_<time>/``), complete for evaluation::

    config.yml, args.yml, command.txt   the resolved zoo entry (with its ``gccp`` map) and the command
    planner.zip                         the frozen motion-planner the options ran (none with
                                        ``--planner scripted``: the scripted pure-pursuit planner)
    decider.zip                         the trained decision-maker
    predictor.pt                        the GCCP predictor trained on the side (learned variants)
    hierarchy.yml                       what ``sb3_gccp evaluate`` loads: files, GCCP variant, world
    episodes.csv                        one row per training episode (task, success, crash, masks on)
    training_curve.png, metrics.json    success and collision rate per episode; where it passed 70 %
    monitor/, tb/                       Monitor CSVs and TensorBoard logs
    checkpoints/                        the latest decider.zip, predictor, optimiser and replay buffer

``--stage all`` trains the planner (``GCCPPlanner-v0`` entry of the same file) and then the decider
with it.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import (
    DECIDER_ENV_ID,
    DECIDER_FILE,
    EPISODES_FILE,
    METRICS_FILE,
    PLANNER_FILE,
    PREDICTOR_FILE,
    SCRIPTED,
    TRAINING_CURVE_FILE,
)
from sb3_gccp.frozen import load_frozen_planner, load_planner
from sb3_gccp.gccp.callback import BUFFER_FILE, STATE_FILE, GCCPCallback
from sb3_gccp.gccp.predictor import load_predictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer
from sb3_gccp.gccp.settings import LEARNED, GCCPSettings
from sb3_gccp.hierarchy import Hierarchy
from sb3_gccp.hyperparams import HyperparamsError, load_hyperparams
from sb3_gccp.training.episodes import rolling_rate, write_episodes
from sb3_gccp.training.planner import train_planner
from sb3_gccp.training.run_folder import (
    StageRequest,
    algorithm_kwargs,
    make_model,
    open_run,
    run_budget,
    write_run_files,
)


def make_decider_env(
    config: IntersectionConfig,
    planner_path: str | None = None,
    torch_threads: int | None = None,
    **kwargs: Any,
) -> gym.Env:
    """``GCCPDecider-v0`` on ``config`` for a vec-env worker, its options run by the frozen planner
    ``planner_path`` (loaded once per process; None: the scripted planner); ``torch_threads`` limits
    torch in that process."""
    if torch_threads is not None:
        th.set_num_threads(torch_threads)
    planner = None if planner_path is None else load_frozen_planner(planner_path, config)
    return gym.make(DECIDER_ENV_ID, config=config, planner=planner, **kwargs)


def gccp_settings(settings: dict[str, Any]) -> GCCPSettings:
    """The ``gccp`` map of a decider entry, validated."""
    try:
        return GCCPSettings.from_dict(settings.get("gccp"))
    except (ValueError, TypeError) as err:
        raise HyperparamsError(str(err)) from err


def train_decider(request: StageRequest) -> Path:
    """Train the decision-maker with the frozen planner ``request.planner``; return the run folder.

    With ``request.resume`` (a decider run folder) training continues from its latest checkpoint,
    predictor, optimiser and replay buffer included, up to the same episode budget.
    """
    if request.torch_threads is not None:
        th.set_num_threads(request.torch_threads)
    scripted = request.planner == Path(SCRIPTED)
    if request.resume is None and not scripted and (request.planner is None or not request.planner.is_file()):
        raise HyperparamsError(f"planner not found: {request.planner} (give --planner PATH.zip)")
    run_dir, settings, seed = open_run(request, DECIDER_ENV_ID, "decider")
    if request.resume is not None:
        scripted = not (run_dir / PLANNER_FILE).is_file()
    gccp = gccp_settings(settings)
    world, n_timesteps, n_envs = run_budget(settings, own_keys=("gccp",))
    predictor = gccp.make_predictor()  # before any folder is made: a bad predictor_init fails here
    if request.resume is None and not scripted:
        assert request.planner is not None
        load_planner(request.planner, world)  # and a planner that does not fit the world
    if request.resume is None:
        write_run_files(run_dir, settings, request)
        if not scripted:
            assert request.planner is not None
            shutil.copyfile(request.planner, run_dir / PLANNER_FILE)

    env = make_vec_env(
        make_decider_env,
        n_envs=n_envs,
        seed=seed,
        env_kwargs={
            "config": world,
            "planner_path": None if scripted else str((run_dir / PLANNER_FILE).resolve()),
            "torch_threads": 1 if n_envs > 1 else None,
        },
        monitor_dir=str(run_dir / "monitor"),
        vec_env_cls=SubprocVecEnv if n_envs > 1 else DummyVecEnv,
    )
    checkpoints = run_dir / "checkpoints"
    resumed = request.resume is not None and (checkpoints / STATE_FILE).is_file()
    buffer = EpisodeReplayBuffer(gccp.buffer_capacity)
    if resumed and (checkpoints / BUFFER_FILE).is_file():
        buffer = EpisodeReplayBuffer.load(checkpoints / BUFFER_FILE, gccp.buffer_capacity)
    if resumed and predictor is not None and gccp.predictor in LEARNED:
        predictor.load_state_dict(load_predictor(checkpoints / PREDICTOR_FILE).state_dict())
    callback = GCCPCallback(gccp, predictor, buffer, seed=seed, progress_bar=request.progress_bar)
    callback.checkpoint_dir = checkpoints
    if resumed:
        callback.restore(checkpoints)
    kwargs = algorithm_kwargs(
        {k: v for k, v in settings.items() if k != "gccp"}, n_timesteps, "DecisionMakerPolicy"
    )
    model = make_model(
        env, run_dir, checkpoints / DECIDER_FILE if resumed else None, seed, request.verbose, kwargs
    )
    try:
        if callback.episodes < gccp.n_episodes and model.num_timesteps < n_timesteps:
            model.learn(
                n_timesteps - model.num_timesteps,
                callback=callback,
                reset_num_timesteps=not resumed,
                tb_log_name="decider",
            )
    finally:
        env.close()
    model.save(run_dir / DECIDER_FILE)
    callback.save(checkpoints, with_model=False)
    shutil.copyfile(run_dir / DECIDER_FILE, checkpoints / DECIDER_FILE)
    if (checkpoints / PREDICTOR_FILE).is_file():
        shutil.copyfile(checkpoints / PREDICTOR_FILE, run_dir / PREDICTOR_FILE)
    write_episodes(callback.history, run_dir / EPISODES_FILE)
    Hierarchy(
        run_dir,
        decider_file=DECIDER_FILE,
        planner_file=SCRIPTED if scripted else PLANNER_FILE,
        predictor=gccp.predictor,
        predictor_weights_file=PREDICTOR_FILE if gccp.predictor in LEARNED else None,
        trained_check=gccp.check,
        trained_world=asdict(world),
    ).write()
    metrics = training_metrics(callback.history, gccp)
    (run_dir / METRICS_FILE).write_text(json.dumps(metrics, indent=2) + "\n")
    plot_training_curve(callback.history, gccp, run_dir / TRAINING_CURVE_FILE)
    return run_dir


def train_all(request: StageRequest) -> tuple[Path, Path]:
    """The main job: the planner, then the decision-maker with it; return both run folders' models."""
    # Check the decider's entry before hours of planner training.
    gccp = gccp_settings(load_hyperparams(request.config_file, DECIDER_ENV_ID))
    planner_request = replace(request, max_episodes=gccp.planner_episodes, n_timesteps=None)
    planner = train_planner(planner_request)
    decider_run = train_decider(replace(request, planner=planner))
    return planner, decider_run


def training_metrics(history: list[dict[str, Any]], gccp: GCCPSettings, window: int = 100) -> dict[str, Any]:
    """Episodes, the success and collision rates of the last ``window`` episodes, and the first
    episode at which the rolling success rate (over ``window`` full episodes) reached 70 % and 90 %."""
    success = rolling_rate([row["success"] for row in history], window)
    crashed = rolling_rate([row["crashed"] for row in history], window)

    def first_above(level: float) -> int | None:
        hits = np.flatnonzero(success[window - 1 :] >= level)
        return int(hits[0] + window) if len(hits) else None

    return {
        "episodes": len(history),
        "mask_after_episodes": gccp.mask_after_episodes,
        "window": window,
        "final_success_rate": float(success[-1]) if len(success) else math.nan,
        "final_collision_rate": float(crashed[-1]) if len(crashed) else math.nan,
        "first_episode_success_70": first_above(0.7),
        "first_episode_success_90": first_above(0.9),
    }


def plot_training_curve(
    history: list[dict[str, Any]], gccp: GCCPSettings, path: Path, window: int = 100
) -> None:
    """Success and collision rate per episode (rolling over ``window``), as in the paper's Fig. 5."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = np.arange(1, len(history) + 1)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(episodes, rolling_rate([r["success"] for r in history], window), label="success")
    ax.plot(episodes, rolling_rate([r["crashed"] for r in history], window), label="collision")
    ax.axhline(0.7, color="grey", lw=0.8, ls=":")
    ax.axhline(0.9, color="grey", lw=0.8, ls=":")
    if gccp.predictor != "none" and gccp.mask_after_episodes < len(history):
        ax.axvline(gccp.mask_after_episodes, color="black", lw=0.8, ls="--", label="GCCP masks on")
    ax.set_xlabel("episode")
    ax.set_ylabel(f"rate (last {window} episodes)")
    ax.set_ylim(0, 1)
    ax.legend(loc="center right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
