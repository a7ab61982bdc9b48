"""The motion-planner stage: MaskablePPO on ``GCCPPlanner-v0``, optionally after cloning an expert.

Run folder: see :mod:`sb3_gccp.training.run_folder`, plus ``planner.zip`` and, with ``imitation``,
``imitation.json``, ``planner_cloned.zip`` and ``imitation_data.npz``.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from sb3_contrib import MaskablePPO
from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnMaxEpisodes

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import PLANNER_ENV_ID, PLANNER_FILE
from sb3_gccp.hyperparams import HyperparamsError
from sb3_gccp.progress import StepBar
from sb3_gccp.training.checkpoints import ModelCheckpointCallback, save_model_checkpoint, write_atomically
from sb3_gccp.training.imitation import BehaviourCloningCallback, ExpertData, ImitationSettings, imitate
from sb3_gccp.training.run_folder import (
    StageRequest,
    algorithm_kwargs,
    continue_model,
    load_model,
    make_run_env,
    new_model,
    open_run,
    prepare_run_folder,
    removed_if_setup_fails,
    resume_checkpoint,
    run_budget,
)


def train_planner(request: StageRequest) -> Path:
    """Train the motion-planner with MaskablePPO on ``GCCPPlanner-v0``; return the model path.

    With an ``imitation`` map in the entry, the policy first clones a scripted expert planner, with
    DAgger rounds if asked (:mod:`sb3_gccp.training.imitation`; ``imitation.json`` records how well, and the
    clone is saved as ``planner_cloned.zip``), and PPO continues from there for ``n_timesteps`` (0:
    cloning only), with cloning steps between its updates if ``imitation.bc_steps`` asks. With
    ``request.resume`` (a run folder), training continues from its newest complete checkpoint with the
    run's own resolved config, up to the same total budget.
    """
    run = open_run(request, PLANNER_ENV_ID, "planner")
    th.set_num_threads(run.options.torch_threads)
    imitation = imitation_settings(run.settings)
    world, n_timesteps, n_envs = run_budget(run.settings, (IMITATION_KEY,), allow_zero=imitation is not None)
    checkpoint = resume_checkpoint(run)
    model = None if checkpoint is None else load_model(checkpoint.file(PLANNER_FILE), run)
    prepare_run_folder(run, request, checkpoint)
    with removed_if_setup_fails(run):
        env = make_run_env(
            PLANNER_ENV_ID, n_envs, run.seed, {"config": world}, run.dir, append=model is not None
        )
    try:  # the env's workers are closed whatever fails from here on
        with removed_if_setup_fails(run):
            if model is None:
                ppo_settings = {k: v for k, v in run.settings.items() if k != IMITATION_KEY}
                model = new_model(env, run, algorithm_kwargs(ppo_settings, n_timesteps))
            else:
                continue_model(model, env, run)
        callbacks: list[BaseCallback] = [
            ModelCheckpointCallback(run.dir, "planner", run.options.save_freq, PLANNER_FILE)
        ]
        if imitation is not None:
            data = imitation_data(
                model, run.dir, world, imitation, run.seed, checkpoint is not None, run.options.progress_bar
            )
            if imitation.bc_steps > 0:
                callbacks.append(BehaviourCloningCallback(data, imitation, run.seed))
        if run.options.progress_bar:
            callbacks.append(StepBar(n_timesteps))
        if request.max_episodes is not None:
            # SB3 counts the limit per worker.
            callbacks.append(StopTrainingOnMaxEpisodes(math.ceil(request.max_episodes / n_envs)))
        remaining = n_timesteps - model.num_timesteps
        if remaining > 0:
            model.learn(
                remaining,
                callback=callbacks,
                reset_num_timesteps=checkpoint is None,
                tb_log_name="planner",
            )
    finally:
        env.close()
    final = save_model_checkpoint(model, run.dir, "planner", PLANNER_FILE)
    path = run.dir / PLANNER_FILE
    write_atomically(path, lambda temporary: shutil.copyfile(final.folder / PLANNER_FILE, temporary))
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
    resumed: bool,
    progress: bool,
) -> ExpertData:
    """A new run (or one resumed before its first checkpoint) clones the expert into ``model`` (writing
    ``imitation.json``, the cloned planner and, if PPO keeps a cloning term, the data set); one resumed
    from a checkpoint reads the data set back."""
    path = run_dir / IMITATION_DATA
    if resumed:
        if settings.bc_steps == 0:
            return ExpertData({}, np.empty(0), np.empty(0), np.empty(0), 0)
        if not path.is_file():
            raise HyperparamsError(f"cannot resume the cloning term: {path} is missing")
        return ExpertData.load(path)
    record, data = imitate(model, world, settings, seed, progress)
    summary = json.dumps(record, indent=2) + "\n"
    write_atomically(run_dir / "imitation.json", lambda temporary: temporary.write_text(summary))
    write_atomically(run_dir / CLONED_PLANNER, model.save)
    if settings.bc_steps > 0:
        write_atomically(path, data.save)
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
