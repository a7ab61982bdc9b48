"""The decider run's model chosen on validation flows (``sb3_gccp.training.choosing``), tables stubbed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gccp_envs.config import TASKS
from sb3_gccp.evaluation import EpisodeResult
from sb3_gccp.training import choosing


def _run_folder(tmp_path: Path, names: list[str]) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "decider.zip").write_bytes(b"final decider")
    (run / "predictor.pt").write_bytes(b"final predictor")
    for name in names:
        folder = run / "candidates" / name
        folder.mkdir(parents=True)
        (folder / "decider.zip").write_bytes(f"decider {name}".encode())
        (folder / "predictor.pt").write_bytes(f"predictor {name}".encode())
    return run


def _stub_episodes(monkeypatch: pytest.MonkeyPatch, overall: dict[str, tuple[float, float]]) -> list[str]:
    """Each candidate's (success, collision) [%] in every task, by the decider file it is evaluated with;
    returns the candidates evaluated, one entry per task."""
    calls: list[str] = []

    def episodes(run_dir: str, files: tuple[str, str | None], task: str, flows: int, n: int) -> list:
        name = Path(files[0]).parent.name or "final"
        calls.append(name)
        success, crashed = (round(rate * n / 100) for rate in overall[name])
        return [
            EpisodeResult(
                task, flows + k, k < success, success <= k < success + crashed, False, False, False, 1, 0.0
            )
            for k in range(n)
        ]

    monkeypatch.setattr(choosing, "_validation_episodes", episodes)
    return calls


@pytest.mark.parametrize(
    ("overall", "chosen"),
    [
        ({"1000": (94.0, 3.0), "1200": (93.0, 1.0), "final": (92.0, 0.0)}, "1000"),  # success first
        ({"1000": (94.0, 3.0), "1200": (94.0, 2.0), "final": (93.0, 0.0)}, "1200"),  # then fewer collisions
        ({"1000": (94.0, 2.0), "1200": (94.0, 2.0), "final": (94.0, 2.0)}, "final"),  # then the later
    ],
)
def test_the_candidate_with_the_most_successes_then_the_fewest_collisions_then_the_latest(
    tmp_path, monkeypatch, overall, chosen
):
    run = _run_folder(tmp_path, ["1000", "1200"])
    calls = _stub_episodes(monkeypatch, overall)
    choice = choosing.choose_model(run, flows=2000, episodes_per_task=100)
    assert choice is not None and choice["chosen"] == chosen
    assert calls == [name for name in ("1000", "1200", "final") for _ in TASKS]
    assert json.loads((run / "choice.json").read_text()) == choice
    if chosen == "final":
        assert (run / "decider.zip").read_bytes() == b"final decider"
        assert not (run / "final").exists()
    else:
        assert (run / "decider.zip").read_bytes() == f"decider {chosen}".encode()
        assert (run / "predictor.pt").read_bytes() == f"predictor {chosen}".encode()
        assert (run / "final" / "decider.zip").read_bytes() == b"final decider"
        assert (run / "final" / "predictor.pt").read_bytes() == b"final predictor"


def test_without_candidates_the_final_model_stays_and_nothing_is_evaluated(tmp_path, monkeypatch):
    run = _run_folder(tmp_path, [])
    calls = _stub_episodes(monkeypatch, {})
    assert choosing.choose_model(run, flows=2000, episodes_per_task=100) is None
    assert calls == [] and not (run / "choice.json").exists()
    assert (run / "decider.zip").read_bytes() == b"final decider"


def test_candidates_are_ordered_by_their_episodes_not_by_name(tmp_path):
    run = _run_folder(tmp_path, ["800", "1000", "1200"])
    assert list(choosing.candidates(run)) == ["800", "1000", "1200"]


def test_the_validation_episodes_are_counted_on_a_bar(tmp_path, monkeypatch, capsys):
    run = _run_folder(tmp_path, ["1000"])
    _stub_episodes(monkeypatch, {"1000": (94.0, 3.0), "final": (92.0, 0.0)})
    choosing.choose_model(run, flows=2000, episodes_per_task=10, progress=True)
    err = capsys.readouterr().err
    assert "validation" in err and "60/60" in err
