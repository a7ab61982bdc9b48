"""The flow-by-flow comparison of two evaluations (benchmarks/paired.py)."""

from __future__ import annotations

import json

import pytest
from helpers import load_benchmark


@pytest.fixture(scope="module")
def paired():
    return load_benchmark("paired")


def evaluation(path, wins: dict[str, list[bool]]):
    """A file in the layout of `sb3_gccp evaluate --json`: one episode per (task, seed 1000 + i)."""
    episodes = [
        {"task": task, "seed": 1000 + i, "success": won, "crashed": not won}
        for task, outcomes in wins.items()
        for i, won in enumerate(outcomes)
    ]
    path.write_text(json.dumps({"table": {}, "episodes": episodes}))
    return str(path)


def test_the_sign_test_counts_only_the_uneven_split(paired):
    assert paired.sign_test(0, 0) == 1.0
    assert paired.sign_test(3, 3) == 1.0
    assert paired.sign_test(5, 0) == pytest.approx(2 / 32)
    assert paired.sign_test(0, 5) == pytest.approx(2 / 32)
    assert paired.sign_test(15, 8) == pytest.approx(0.2100, abs=1e-4)


def test_flows_are_paired_by_task_and_seed(paired, tmp_path, capsys):
    a = evaluation(tmp_path / "a.json", {"left": [True, False, False, True], "right": [True, True]})
    b = evaluation(tmp_path / "b.json", {"left": [True, True, True, False], "right": [True, True]})
    paired.main([a, b])
    line = capsys.readouterr().out.strip()
    assert "(6 flows)" in line
    assert "A 66.7 %  B 83.3 %  B-A +16.7 points  B only 2  A only 1" in line
    assert "sign test p 1.000" in line


def test_pairs_pool_their_discordant_flows(paired, tmp_path, capsys):
    flows = {"left": [False] * 6}
    a1, a2 = evaluation(tmp_path / "a1.json", flows), evaluation(tmp_path / "a2.json", flows)
    b1 = evaluation(tmp_path / "b1.json", {"left": [True] * 3 + [False] * 3})
    b2 = evaluation(tmp_path / "b2.json", {"left": [True] * 3 + [False] * 3})
    paired.main([a1, b1, a2, b2])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3
    assert "B only 3  A only 0  sign test p 0.250" in lines[0]
    assert lines[2].startswith("pooled over 2 pairs")
    assert "B only 6  A only 0  sign test p 0.031" in lines[2]
    assert "95 % interval [+" in lines[2]


@pytest.mark.parametrize(
    "case, message",
    [
        ("odd", "come in pairs"),
        ("other flows", "not evaluated on the same flows"),
        ("not json", "not the --json file of sb3_gccp evaluate"),
    ],
)
def test_bad_input_fails_in_one_line(paired, tmp_path, capsys, case, message):
    a = evaluation(tmp_path / "a.json", {"left": [True, False]})
    if case == "odd":
        files = [a]
    elif case == "other flows":
        files = [a, evaluation(tmp_path / "b.json", {"straight": [True, False]})]
    else:
        (tmp_path / "b.json").write_text("no")
        files = [a, str(tmp_path / "b.json")]
    with pytest.raises(SystemExit) as exit_info:
        paired.main(files)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]
