"""Running a command line as a user does, and what a refusal must look like."""

from __future__ import annotations

import subprocess
import sys


def run_cli(module: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True
    )


def assert_refused(proc: subprocess.CompletedProcess, *words: str) -> None:
    """Exit 2, no traceback, one line on stderr naming ``words``."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    for word in words:
        assert word in lines[0], lines[0]
