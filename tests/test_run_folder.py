"""Run folders: the run options (recorded in ``args.yml``, reused by a resume unless given again) and the
seeds of a resumed run."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import TINY_PLANNER_HYPERPARAMS
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig
from sb3_gccp.constants import PLANNER_ENV_ID
from sb3_gccp.training.run_folder import Run, RunOptions, continue_model, make_run_env


def test_a_resume_keeps_the_recorded_options_unless_given_again():
    recorded = {"seed": 3, "save_freq": 500, "verbose": 1, "torch_threads": 2, "progress_bar": False}
    given = {"save_freq": None, "verbose": 2, "torch_threads": None, "progress_bar": None}
    options = RunOptions.resolve(given, recorded)
    assert options == RunOptions(save_freq=500, verbose=2, torch_threads=2, progress_bar=False)
    assert options.to_dict() == {"save_freq": 500, "verbose": 2, "torch_threads": 2, "progress_bar": False}


def test_a_new_run_or_one_recorded_before_options_were_takes_the_defaults():
    not_given = dict.fromkeys(("save_freq", "verbose", "torch_threads", "progress_bar"))
    assert RunOptions.resolve(not_given) == RunOptions.resolve(not_given, {"seed": 0}) == RunOptions()
    assert RunOptions() == RunOptions(save_freq=10_000, verbose=0, torch_threads=1, progress_bar=True)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"save_freq": 0}, "--save-freq must be a positive integer, got 0"),
        ({"save_freq": 2.5}, "--save-freq must be a positive integer, got 2.5"),
        ({"torch_threads": -1}, "--torch-threads must be a positive integer, got -1"),
        ({"verbose": -1}, "-v/--verbose must be a non-negative integer, got -1"),
        ({"progress_bar": "yes"}, "progress_bar must be true or false, got 'yes'"),
    ],
)
def test_an_option_out_of_range_is_named_with_its_value(values, message):
    with pytest.raises(ValueError, match=f"^{message}$".replace(".", r"\.")):
        RunOptions.resolve(values)


def test_a_resumed_model_plays_on_past_the_seeds_the_run_started_with(tmp_path):
    settings = TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"]
    world = IntersectionConfig.from_dict(settings["env_kwargs"])
    run = Run(tmp_path, settings, seed=3, options=RunOptions(), resumed=True)
    model = MaskablePPO("MultiInputPolicy", make_run_env(PLANNER_ENV_ID, 1, 3, {"config": world}, tmp_path))
    model.num_timesteps = 40  # as loaded from a checkpoint at 40 steps

    def first_observation(seed: int | None = None) -> np.ndarray:
        env = make_run_env(PLANNER_ENV_ID, 1, 3, {"config": world}, tmp_path)
        if seed is None:
            continue_model(model, env, run)
        else:
            env.seed(seed)
        return np.concatenate([np.ravel(v) for v in env.reset().values()])

    resumed = first_observation()
    assert np.array_equal(resumed, first_observation(3 + 40))
    assert not np.array_equal(resumed, first_observation(3))  # not the run's first episode again
