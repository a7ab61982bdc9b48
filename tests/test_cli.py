"""``sb3_gccp rollout``: the scripted hierarchy from the command line, with and without a progress bar."""

from __future__ import annotations

import json

import pytest

from sb3_gccp.cli import main


@pytest.mark.parametrize("progress", [[], ["--no-progress"]])
def test_rollout_writes_its_table(tmp_path, capsys, progress):
    out = tmp_path / "rollout.json"
    args = ["rollout", "--tasks", "right", "--episodes-per-task", "1", "--json", str(out), *progress]
    assert main([*args, "--set", "spawn_probability=0", "--set", "duration=8"]) == 0
    written = json.loads(out.read_text())
    assert "| right | 1 |" in capsys.readouterr().out
    assert set(written["table"]) == {"right", "overall"}
    (episode,) = written["episodes"]
    assert (episode["task"], episode["seed"], episode["steps"]) == ("right", 0, 8)  # 8 s: 8 decisions
    assert episode["timeout"]
