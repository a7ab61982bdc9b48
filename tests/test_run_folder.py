"""Run folders: the run options, recorded in ``args.yml`` and reused by a resume unless given again."""

from __future__ import annotations

import pytest

from sb3_gccp.training.run_folder import RunOptions


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
