"""The motion-planner stage: MaskablePPO on ``GCCPPlanner-v0``, optionally after cloning an expert.

Run folder: see :mod:`sb3_gccp.training.run_folder`, plus ``planner.zip`` and, with ``imitation``,
``imitation.json``, ``planner_cloned.zip`` and ``imitation_data.npz``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from sb3_contrib import MaskablePPO
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback, StopTrainingOnMaxEpisodes

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import PLANNER_ENV_ID, PLANNER_FILE
from sb3_gccp.hyperparams import HyperparamsError
from sb3_gccp.progress import StepBar
from sb3_gccp.training.imitation import BehaviourCloningCallback, ExpertData, ImitationSettings, imitate
from sb3_gccp.training.run_folder import (
    StageRequest,
    algorithm_kwargs,
    latest_checkpoint,
    make_model,
    make_run_env,
    open_run,
    run_budget,
    write_run_files,
)


def train_planner(request: StageRequest) -> Path:
    """Train the motion-planner with MaskablePPO on ``GCCPPlanner-v0``; return the model path.

    With an ``imitation`` map in the entry, the policy first clones a scripted expert planner, with
    DAgger rounds if asked (:mod:`sb3_gccp.training.imitation`; ``imitation.json`` records how well, and the
    clone is saved as ``planner_cloned.zip``), and PPO continues from there for ``n_timesteps`` (0:
    cloning only), with cloning steps between its updates if ``imitation.bc_steps`` asks. With
    ``request.resume`` (a run folder), training continues from its last checkpoint with the run's own
    resolved config, up to the same total budget.
    """
    if request.torch_threads is not None:
        th.set_num_threads(request.torch_threads)
    run_dir, settings, seed = open_run(request, PLANNER_ENV_ID, "planner")
    imitation = imitation_settings(settings)
    world, n_timesteps, n_envs = run_budget(settings, (IMITATION_KEY,), allow_zero=imitation is not None)
    if request.resume is None:
        write_run_files(run_dir, settings, request)
    env = make_run_env(PLANNER_ENV_ID, n_envs, seed, world, run_dir)
    checkpoint = latest_checkpoint(run_dir) if request.resume is not None else None
    ppo_settings = {k: v for k, v in settings.items() if k != IMITATION_KEY}
    model = make_model(
        env, run_dir, checkpoint, seed, request.verbose, algorithm_kwargs(ppo_settings, n_timesteps)
    )
    callbacks: list[BaseCallback] = [
        CheckpointCallback(
            max(request.save_freq // n_envs, 1), str(run_dir / "checkpoints"), name_prefix="planner"
        )
    ]
    if imitation is not None:
        data = imitation_data(model, run_dir, world, imitation, seed, checkpoint, request.progress_bar)
        if imitation.bc_steps > 0:
            callbacks.append(BehaviourCloningCallback(data, imitation, seed))
    if request.progress_bar:
        callbacks.append(StepBar(n_timesteps))
    if request.max_episodes is not None:
        # SB3 counts the limit per worker.
        callbacks.append(StopTrainingOnMaxEpisodes(math.ceil(request.max_episodes / n_envs)))
    remaining = n_timesteps - model.num_timesteps
    try:
        if remaining > 0:
            model.learn(
                remaining,
                callback=callbacks,
                reset_num_timesteps=checkpoint is None,
                tb_log_name="planner",
            )
    finally:
        env.close()
    path = run_dir / PLANNER_FILE
    model.save(path)
    return path


CLONED_PLANNER = "planner_cloned.zip"
"""The planner as cloned, before PPO, in the run folder of a planner stage with ``imitation``."""
IMITATION_DATA = "imitation_data.npz"
"""The cloning's data set in the run folder (the behaviour-cloning term of PPO reads it on resume)."""


def imitation_data(
    model: MaskablePPO,
    run_dir: Path,
    world: IntersectionConfig,
    settings: ImitationSettings,
    seed: int,
    checkpoint: Path | None,
    progress: bool,
) -> ExpertData:
    """A new run clones the expert into ``model`` (writing ``imitation.json``, the cloned planner and,
    if PPO keeps a cloning term, the data set); a resumed one reads the data set back."""
    path = run_dir / IMITATION_DATA
    if checkpoint is not None:
        if settings.bc_steps == 0:
            return ExpertData({}, np.empty(0), np.empty(0), np.empty(0), 0)
        if not path.is_file():
            raise HyperparamsError(f"cannot resume the cloning term: {path} is missing")
        return ExpertData.load(path)
    record, data = imitate(model, world, settings, seed, progress)
    (run_dir / "imitation.json").write_text(json.dumps(record, indent=2) + "\n")
    model.save(run_dir / CLONED_PLANNER)
    if settings.bc_steps > 0:
        data.save(path)
    return data


IMITATION_KEY = "imitation"
"""The planner entry's own key: imitation of a scripted expert planner before PPO."""


def imitation_settings(settings: dict[str, Any]) -> ImitationSettings | None:
    """The planner entry's ``imitation`` map, validated; None without one."""
    if IMITATION_KEY not in settings:
        return None
    try:
        return ImitationSettings.from_dict(settings[IMITATION_KEY])
    except (ValueError, TypeError) as err:
        raise HyperparamsError(str(err)) from err
