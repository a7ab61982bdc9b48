"""``export`` with ``--set``/``--mask``: a trained hierarchy under another world setting or GCCP check."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sb3_gccp.cli import main
from sb3_gccp.export import export_run
from sb3_gccp.hierarchy import load_hierarchy

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"
HIERARCHY = "reference/scripted_planner"  # a shipped hierarchy as trained (runs fast: scripted planner)


def test_export_lists_replaced_settings_as_overrides_and_keeps_what_was_trained(tmp_path):
    source = PRETRAINED / HIERARCHY
    export_run(source, tmp_path / "out", {"scripted_turn_speed": 4.0}, {"mask_yield_margin": 0.5})
    before = yaml.safe_load((source / "hierarchy.yml").read_text())
    after = yaml.safe_load((tmp_path / "out" / "hierarchy.yml").read_text())
    assert after["world"] == before["world"] and after.get("mask_yield_margin") == before.get(
        "mask_yield_margin"
    )
    assert after["overrides"] == {"world": {"scripted_turn_speed": 4.0}, "mask": {"mask_yield_margin": 0.5}}
    hierarchy = load_hierarchy(tmp_path / "out", allow_overrides=True)
    assert hierarchy.check.yield_margin == 0.5 and hierarchy.check.margin == before["mask_margin"]
    assert hierarchy.make_env().config.scripted_turn_speed == 4.0
    # exporting again adds to the overrides
    export_run(tmp_path / "out", tmp_path / "again", {"duration": 20.0}, {})
    again = yaml.safe_load((tmp_path / "again" / "hierarchy.yml").read_text())
    assert again["overrides"]["world"] == {"scripted_turn_speed": 4.0, "duration": 20.0}


def test_a_hierarchy_with_overrides_runs_only_when_asked(tmp_path, capsys):
    export_run(PRETRAINED / HIERARCHY, tmp_path / "out", {}, {"mask_margin": 0.5})
    with pytest.raises(ValueError, match=r"not trained with \(overrides: mask.mask_margin\)"):
        load_hierarchy(tmp_path / "out")
    args = ["evaluate", "--model", str(tmp_path / "out"), "--episodes-per-task", "1", "--no-progress"]
    assert main(args) == 2
    assert "--allow-overrides" in capsys.readouterr().err.strip().splitlines()[-1]
    assert main([*args, "--allow-overrides", "--set", "duration=2"]) == 0


def test_a_hierarchy_as_trained_has_no_overrides():
    hierarchy = load_hierarchy(PRETRAINED / HIERARCHY)
    assert hierarchy.overrides == {}


@pytest.mark.parametrize(
    ("source", "args", "message"),
    [
        (HIERARCHY, ["--set", "scripted_turn_sped=4"], "unknown intersection config key(s)"),
        (HIERARCHY, ["--set", "scripted_turn_speed=0"], "scripted_turn_speed must be a positive number"),
        (HIERARCHY, ["--mask", "mask_yield_margin=-1"], "mask_yield_margin must be a non-negative number"),
        ("baselines/ppo", ["--set", "duration=20"], "--set and --mask change hierarchy runs only"),
    ],
)
def test_export_rejects_a_bad_replacement_in_one_line_and_writes_nothing(
    tmp_path, capsys, source, args, message
):
    assert main(["export", str(PRETRAINED / source), str(tmp_path / "out"), *args]) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error
    assert not (tmp_path / "out").exists()
