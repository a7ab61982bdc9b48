"""The decision-maker stage: MaskablePPO on ``GCCPDecider-v0`` with the frozen planner and GCCP.

Run folder (``<log_folder>/decider/GCCPDecider-v0_<seed>_<time>/``), complete for evaluation::

    config.yml, args.yml, command.txt   the resolved zoo entry (with its ``gccp`` map) and the command
    planner.zip                         the frozen motion-planner the options ran (none with
                                        ``--planner scripted``: the scripted pure-pursuit planner)
    decider.zip                         the trained decision-maker: the final one or, with
                                        ``gccp.choose_on_flows``, the candidate chosen on validation flows
    predictor.pt                        the GCCP predictor trained on the side (learned variants), the
                                        decider's own
    candidates/, final/, choice.json    with ``gccp.choose_on_flows``: the candidates, the final model
                                        when another was chosen, every candidate's validation table
                                        (:mod:`sb3_gccp.training.choosing`)
    hierarchy.yml                       what ``sb3_gccp evaluate`` loads: files, GCCP variant, world
    episodes.csv                        per training episode: task, success, crash, masks on, clock
    training_curve.png, metrics.json    success and collision rate per episode; where it passed 70 %
    monitor/, tb/                       Monitor CSVs and TensorBoard logs
    checkpoints/                        the two newest checkpoints: decider.zip, predictor, optimiser,
                                        replay buffer, episode rows (:mod:`sb3_gccp.training.checkpoints`)

``--stage all`` trains the planner (``GCCPPlanner-v0`` entry of the same file) and then the decider
with it.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from sb3_contrib import MaskablePPO
from stable_baselines3.common.callbacks import BaseCallback

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import (
    CHOICE_FILE,
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
from sb3_gccp.gccp.callback import BUFFER_FILE, GCCPCallback, StepOverlap
from sb3_gccp.gccp.predictor import load_predictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer
from sb3_gccp.gccp.settings import LEARNED, GCCPSettings
from sb3_gccp.hierarchy import Hierarchy
from sb3_gccp.hyperparams import HyperparamsError
from sb3_gccp.training.checkpoints import Checkpoint, write_atomically
from sb3_gccp.training.choosing import choose_model
from sb3_gccp.training.episodes import rolling_rate
from sb3_gccp.training.planner import train_planner
from sb3_gccp.training.run_folder import (
    Run,
    StageRequest,
    algorithm_kwargs,
    continue_model,
    load_model,
    make_run_env,
    new_model,
    open_run,
    prepare_run_folder,
    removed_if_setup_fails,
    requested_settings,
    resume_checkpoint,
    run_budget,
)
from sb3_gccp.training.workers import start_worker_server


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


def train_decider(request: StageRequest, callback: BaseCallback | None = None) -> Path:
    """Train the decision-maker with the frozen planner ``request.planner``; return the run folder.

    With ``request.resume`` (a decider run folder) training continues from its newest complete
    checkpoint, predictor, optimiser and replay buffer included, up to the same episode budget.

    :param callback: an extra SB3 callback beside the GCCP callback (``sb3_gccp tune``'s pruning)
    """
    scripted = request.planner == Path(SCRIPTED)
    if request.resume is None and not scripted and (request.planner is None or not request.planner.is_file()):
        raise HyperparamsError(f"planner not found: {request.planner} (give --planner PATH.zip)")
    run = open_run(request, DECIDER_ENV_ID, "decider")
    th.set_num_threads(run.options.torch_threads)
    if run.resumed:
        scripted = not (run.dir / PLANNER_FILE).is_file()
    gccp = gccp_settings(run.settings)
    world, n_timesteps, n_envs = run_budget(run.settings, own_keys=("gccp",))
    if n_envs > 1:
        start_worker_server(make_decider_env.__module__)  # its workers import this module
    th.manual_seed(run.seed)  # the predictor's first weights: the same seed, the same run
    predictor = gccp.make_predictor()  # before any folder is made: a bad predictor_init fails here
    if not run.resumed and not scripted:
        assert request.planner is not None
        load_planner(request.planner, world)  # and a planner that does not fit the world
    checkpoint = resume_checkpoint(run)
    gccp_callback = GCCPCallback(
        gccp,
        predictor,
        EpisodeReplayBuffer(gccp.buffer_capacity),
        seed=run.seed,
        progress_bar=run.options.progress_bar,
        run_dir=run.dir,
        world=world,
    )
    model = None if checkpoint is None else restore_decider(checkpoint, gccp_callback, run)
    planner = request.planner
    copies = {} if scripted or planner is None else {PLANNER_FILE: partial(shutil.copyfile, planner)}
    prepare_run_folder(run, request, checkpoint, copies)
    with removed_if_setup_fails(run):
        env = make_run_env(
            make_decider_env,
            n_envs,
            run.seed,
            {
                "config": world,
                "planner_path": None if scripted else str((run.dir / PLANNER_FILE).resolve()),
                "torch_threads": 1 if n_envs > 1 else None,
            },
            run.dir,
            append=model is not None,
            subprocesses=True,
        )
        env = StepOverlap(env, gccp_callback.run_next)
    try:  # the env's workers are closed whatever fails from here on
        with removed_if_setup_fails(run):
            if model is None:
                kwargs = algorithm_kwargs(
                    {k: v for k, v in run.settings.items() if k != "gccp"}, n_timesteps, "DecisionMakerPolicy"
                )
                model = new_model(env, run, kwargs)
            else:
                continue_model(model, env, run)
        if gccp_callback.episodes < gccp.n_episodes and model.num_timesteps < n_timesteps:
            model.learn(
                n_timesteps - model.num_timesteps,
                callback=gccp_callback if callback is None else [gccp_callback, callback],
                reset_num_timesteps=checkpoint is None,
                tb_log_name="decider",
            )
    finally:
        env.close()
    write_decider_run(run.dir, gccp_callback.checkpoint(model), gccp_callback.history, gccp, scripted, world)
    if gccp_callback.choosing:
        assert gccp.choose_on_flows is not None
        print(f"choosing the run's model on validation flows from {gccp.choose_on_flows} (see {CHOICE_FILE})")
        choice = choose_model(
            run.dir,
            gccp.choose_on_flows,
            gccp.choose_episodes_per_task,
            workers=n_envs,
            progress=run.options.progress_bar,
        )
        if choice is not None:
            chosen = choice["chosen"]
            print(f"the run's model: after {chosen} episodes, chosen on validation flows ({CHOICE_FILE})")
    return run.dir


def restore_decider(checkpoint: Checkpoint, callback: GCCPCallback, run: Run) -> MaskablePPO:
    """The decision-maker of a checkpoint; the callback gets its predictor, replay buffer and state."""
    gccp = callback.settings
    if BUFFER_FILE in checkpoint.files:
        callback.buffer = EpisodeReplayBuffer.load(checkpoint.file(BUFFER_FILE), gccp.buffer_capacity)
    if callback.predictor is not None and gccp.predictor in LEARNED:
        callback.predictor.load_state_dict(load_predictor(checkpoint.file(PREDICTOR_FILE)).state_dict())
    callback.restore(checkpoint)
    return load_model(checkpoint.file(DECIDER_FILE), run)


def write_decider_run(
    run_dir: Path,
    final: Checkpoint,
    history: list[dict[str, Any]],
    gccp: GCCPSettings,
    scripted: bool,
    world: IntersectionConfig,
) -> None:
    """The files of a finished decider run, from its final checkpoint: what ``evaluate`` loads
    (``decider.zip``, ``predictor.pt``, ``hierarchy.yml``), ``episodes.csv``, ``metrics.json`` and the
    training curve."""
    for name in (DECIDER_FILE, PREDICTOR_FILE, EPISODES_FILE):
        if name in final.files:
            write_atomically(run_dir / name, partial(shutil.copyfile, final.file(name)))
    Hierarchy(
        run_dir,
        decider_file=DECIDER_FILE,
        planner_file=SCRIPTED if scripted else PLANNER_FILE,
        predictor=gccp.predictor,
        predictor_weights_file=PREDICTOR_FILE if gccp.predictor in LEARNED else None,
        trained_check=gccp.check,
        trained_world=asdict(world),
    ).write()
    metrics = json.dumps(training_metrics(history, gccp), indent=2) + "\n"
    write_atomically(run_dir / METRICS_FILE, lambda path: path.write_text(metrics))
    write_atomically(run_dir / TRAINING_CURVE_FILE, lambda path: plot_training_curve(history, gccp, path))


def train_all(request: StageRequest) -> tuple[Path, Path]:
    """The main job: the planner, then the decision-maker with it; return both run folders' models."""
    # Check the decider's entry before hours of planner training.
    gccp = gccp_settings(requested_settings(request, DECIDER_ENV_ID))
    planner_request = replace(request, max_episodes=gccp.planner_episodes, n_timesteps=None, gccp={})
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
