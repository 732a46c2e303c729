"""A reference result: a study run's report, tables and figures copied into a folder of
their own and stamped with the commit, command and machine that made them.

``kpstudy publish results/standard docs/results/standard --commit … --command …``
writes the folder the repository keeps as the study's result; a rerun is held against
it with ``kpstudy compare docs/results/standard results/standard`` (tables cell by cell,
times aside).
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
from pathlib import Path

#: What a reference keeps of a run: the report and what it shows.
KEPT = ("REPORT.md", "tables/*.csv", "tables/*.md", "tables/*.json", "figures/*.png")


def publish(run, dest, *, commit: str, command: str) -> Path:
    """Copy the run ``run`` (a ``results/<profile>`` folder with ``REPORT.md``) into
    ``dest`` and write ``dest/STAMP.md``.

    ``commit`` is the git commit of the code that ran (7–40 hex digits), ``command`` the
    command line that ran it. The stamp lists both, this machine (cores, processor,
    torch) and each notebook's last execution in seconds (papermill's record; a campaign
    resumed from its store shows only its last part: the report's cost table sums every
    instance). ``dest`` is replaced whole, atomically. Returns ``dest``.

    Raises ``ValueError`` naming the argument for a run without a report or tables, a
    commit that is not hex, or an empty command.
    """
    from kpstudy.io import check_writable, staged_directory, write_text_atomic

    run, dest = Path(run), Path(dest)
    if not (run / "REPORT.md").is_file() or not list(run.glob("tables/*.csv")):
        raise ValueError(
            f"run: expected a results folder with REPORT.md and tables/*.csv, got {str(run)!r}"
        )
    if not re.fullmatch(r"[0-9a-f]{7,40}", commit):
        raise ValueError(f"commit: expected 7 to 40 hex digits (git rev-parse), got {commit!r}")
    if not command.strip():
        raise ValueError("command: expected the command line that made the run, got ''")
    check_writable(dest, "dest")
    files = sorted({p for pattern in KEPT for p in run.glob(pattern)})
    with staged_directory(dest, {"run": str(run.resolve()), "commit": commit}) as (staging, _):
        for source in files:
            target = staging / source.relative_to(run)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
        write_text_atomic(staging / "STAMP.md", stamp_markdown(run, commit, command))
    return dest


def notebook_seconds(run) -> dict[str, float]:
    """``{notebook name: seconds of its last execution}`` from the papermill metadata of
    ``run/notebooks/*.ipynb`` (notebooks without the record are left out)."""
    seconds = {}
    for path in sorted(Path(run).glob("notebooks/*.ipynb")):
        record = json.loads(path.read_text()).get("metadata", {}).get("papermill", {})
        if isinstance(record.get("duration"), (int, float)):
            seconds[path.stem] = float(record["duration"])
    return seconds


def stamp_markdown(run, commit: str, command: str) -> str:
    """The text of ``STAMP.md``: commit, command, machine and notebook times."""
    import torch

    seconds = notebook_seconds(run)
    lines = [
        "# What made this result",
        "",
        f"- commit: `{commit}`",
        f"- command: `{command}`",
        f"- machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}, torch {torch.__version__}",
        "",
        "| notebook | seconds (last execution) |",
        "|---|---|",
        *(f"| {name} | {value:.0f} |" for name, value in seconds.items()),
        f"| total | {sum(seconds.values()):.0f} |",
        "",
    ]
    return "\n".join(lines)
