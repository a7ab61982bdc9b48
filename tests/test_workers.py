"""The fork server that worker processes start from."""

from __future__ import annotations

import subprocess
import sys

import pytest

WORKER_SEES = """
import multiprocessing, sys
from sb3_gccp.training.workers import start_worker_server

def preloaded() -> bool:
    return "mailbox" in sys.modules

if __name__ == "__main__":
    if sys.argv[1] == "start":
        start_worker_server("mailbox")
    with multiprocessing.get_context("forkserver").Pool(1) as pool:
        print(pool.apply(preloaded), "mailbox" in sys.modules)
"""


@pytest.mark.parametrize(("start", "expected"), [("start", "True False"), ("no", "False False")])
def test_worker_processes_start_with_the_modules_the_fork_server_imported(tmp_path, start, expected):
    script = tmp_path / "workers.py"
    script.write_text(WORKER_SEES)
    result = subprocess.run([sys.executable, str(script), start], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == expected.split()
