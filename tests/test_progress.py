"""Progress bars: live on a terminal, plain lines in a log file."""

from __future__ import annotations

from sb3_gccp import progress


def test_bar_writes_plain_lines_when_stderr_is_not_a_terminal(capsys, monkeypatch):
    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)
    assert list(progress.new_bar(range(3), desc="episodes", unit="ep")) == [0, 1, 2]
    lines = capsys.readouterr().err.splitlines()
    assert "\r" not in "".join(lines)
    assert lines[0].startswith("episodes:   0%") and "3/3" in lines[-1]


def test_a_log_file_gets_a_line_a_minute_not_a_line_per_update(capsys):
    bar = progress.new_bar(total=1000, desc="steps")
    for _ in range(1000):
        bar.update()
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "1000/1000" in lines[-1]  # the first draw and the last


def test_disabled_bar_is_silent(capsys):
    assert list(progress.new_bar(range(3), enabled=False)) == [0, 1, 2]
    assert capsys.readouterr().err == ""
