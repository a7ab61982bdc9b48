"""Checkpoints: atomic files, a marker written last, the two newest kept, a damaged one passed over."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sb3_gccp.training.checkpoints import (
    MARKER_FILE,
    find_checkpoint,
    resume_message,
    rewind_run,
    save_checkpoint,
    write_atomically,
)

MONITOR_HEADER = '#{"t_start": 1700000000.0, "env_id": "GCCPDecider-v0"}\nr,l,t\n'


def monitor_file(run: Path, rows: int) -> Path:
    """``monitor/0.monitor.csv`` with ``rows`` episodes, as SB3's Monitor writes it."""
    path = run / "monitor" / "0.monitor.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(MONITOR_HEADER + "".join(f"1.0,2,{k}.0\n" for k in range(rows)))
    return path


def save(run: Path, steps: int, episodes: int) -> None:
    """A checkpoint at ``steps`` after ``episodes`` episodes: a model and an episode log."""
    monitor_file(run, episodes)
    files = {
        "decider.zip": lambda path: path.write_bytes(bytes(range(256)) * steps),
        "episodes.csv": lambda path: path.write_text(f"episodes: {episodes}\n"),
    }
    save_checkpoint(run, "decider", steps, files)


def folders(run: Path) -> list[str]:
    return sorted((p.name for p in (run / "checkpoints").iterdir()), key=lambda n: int(n.split("_")[1]))


def test_a_checkpoint_records_its_files_and_the_monitor_lengths_in_its_marker(tmp_path):
    save(tmp_path, 8, 4)
    marker = json.loads((tmp_path / "checkpoints" / "decider_8_steps" / MARKER_FILE).read_text())
    assert marker["steps"] == 8 and marker["episodes"] == 4
    assert marker["files"]["decider.zip"]["bytes"] == 8 * 256
    assert marker["monitor"] == {"0.monitor.csv": (tmp_path / "monitor" / "0.monitor.csv").stat().st_size}
    # Written through temporary names that are gone.
    assert sorted(p.name for p in (tmp_path / "checkpoints" / "decider_8_steps").iterdir()) == [
        MARKER_FILE,
        "decider.zip",
        "episodes.csv",
    ]


def test_only_the_two_newest_complete_checkpoints_are_kept(tmp_path):
    for k in range(1, 5):
        save(tmp_path, 8 * k, 4 * k)
    assert folders(tmp_path) == ["decider_24_steps", "decider_32_steps"]


def test_a_write_that_fails_leaves_no_marker_and_the_previous_checkpoint_is_resumed(tmp_path):
    save(tmp_path, 8, 4)

    def killed(path: Path) -> None:
        path.write_bytes(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, "decider", 16, {"decider.zip": killed})
    incomplete = tmp_path / "checkpoints" / "decider_16_steps"
    assert incomplete.is_dir() and not (incomplete / "decider.zip").exists()  # only its temporary file
    checkpoint, damaged = find_checkpoint(tmp_path)
    assert checkpoint is not None and checkpoint.steps == 8
    assert damaged == {incomplete: f"no {MARKER_FILE} (interrupted while written)"}


def test_resume_passes_over_a_damaged_newest_checkpoint_and_says_so_in_one_line(tmp_path):
    save(tmp_path, 8, 4)
    save(tmp_path, 16, 6)
    model = tmp_path / "checkpoints" / "decider_16_steps" / "decider.zip"
    model.write_bytes(model.read_bytes()[:100])  # an unreadable zip
    checkpoint, damaged = find_checkpoint(tmp_path)
    assert checkpoint is not None and checkpoint.name == "checkpoints/decider_8_steps"
    message = resume_message(tmp_path, checkpoint, damaged)
    assert message == (
        f"resuming {tmp_path} from checkpoints/decider_8_steps (8 steps, 4 episodes); "
        "passed over checkpoints/decider_16_steps: decider.zip does not match its checksum"
    )
    assert "\n" not in message


def test_rewinding_to_a_checkpoint_cuts_the_monitor_back_and_deletes_the_newer_checkpoints(tmp_path):
    save(tmp_path, 8, 4)
    save(tmp_path, 16, 6)
    (tmp_path / "checkpoints" / "decider_16_steps" / MARKER_FILE).unlink()
    monitor = monitor_file(tmp_path, 9)  # episodes after the checkpoint, to be played again
    checkpoint, _ = find_checkpoint(tmp_path)
    rewind_run(tmp_path, checkpoint)
    assert folders(tmp_path) == ["decider_8_steps"]
    assert monitor.read_text() == MONITOR_HEADER + "".join(f"1.0,2,{k}.0\n" for k in range(4))
    rewind_run(tmp_path, None)  # starting over: no Monitor rows are kept
    assert not monitor.exists() and folders(tmp_path) == []


def test_a_checkpoint_saved_again_at_the_same_step_count_is_kept_as_it_is(tmp_path):
    save(tmp_path, 8, 4)
    before = (tmp_path / "checkpoints" / "decider_8_steps" / MARKER_FILE).read_text()
    save(tmp_path, 8, 5)
    assert (tmp_path / "checkpoints" / "decider_8_steps" / MARKER_FILE).read_text() == before


def test_loose_checkpoint_files_of_the_older_layout_are_refused_rather_than_started_over(tmp_path):
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "decider.zip").write_bytes(b"old")
    with pytest.raises(ValueError, match=r"older sb3_gccp \(decider\.zip\)"):
        find_checkpoint(tmp_path)


def test_a_failed_atomic_write_leaves_the_old_file_whole(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("old")

    def fails(temporary: Path) -> None:
        temporary.write_text("new, half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        write_atomically(path, fails)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]  # no half-written temporary left
    write_atomically(path, lambda temporary: temporary.write_text("new"))
    assert path.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]
