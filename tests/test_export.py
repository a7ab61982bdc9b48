"""``export`` with ``--set``/``--mask``: a trained hierarchy under another world setting or GCCP check."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sb3_gccp.cli import main
from sb3_gccp.export import export_run
from sb3_gccp.hierarchy import load_hierarchy

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"
HIERARCHY = "seeds/seed1"  # a shipped hierarchy run as trained


def test_export_writes_the_replaced_settings_and_keeps_the_rest(tmp_path):
    source = PRETRAINED / HIERARCHY
    export_run(source, tmp_path / "out", {"scripted_turn_speed": 4.0}, {"mask_yield_margin": 0.5})
    before = yaml.safe_load((source / "hierarchy.yml").read_text())
    after = yaml.safe_load((tmp_path / "out" / "hierarchy.yml").read_text())
    assert after["mask_yield_margin"] == 0.5 and after["world"]["scripted_turn_speed"] == 4.0
    assert list(after)[-1] == "world"  # the check's settings stay before the world
    assert {k: v for k, v in after["world"].items() if k != "scripted_turn_speed"} == {
        k: v for k, v in before["world"].items() if k != "scripted_turn_speed"
    }
    hierarchy = load_hierarchy(tmp_path / "out")
    assert hierarchy.mask_yield_margin == 0.5 and hierarchy.mask_margin == before["mask_margin"]
    assert hierarchy.make_env().config.scripted_turn_speed == 4.0


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
