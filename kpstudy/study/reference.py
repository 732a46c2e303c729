"""What made a study run, and a run kept as a reference result.

Every stage ``python -m kpstudy reproduce`` runs adds a line to the run's
``runs.jsonl`` (:func:`log_stage`): the stage, its seconds, whether it finished, the git
commit and code fingerprint that ran it and the command, so a run that spans several
invocations (an interruption, a resume in a later session) still says what it cost and
what made it. ``kpstudy publish results/standard docs/results/standard`` (:func:`publish`)
copies the run's report, tables and figures into a folder of their own, stamped with
that record and the machine; a rerun is held against it with ``kpstudy compare
docs/results/standard results/standard`` (tables cell by cell, times aside).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import shutil
import subprocess
from pathlib import Path

#: What a reference keeps of a run: the report and what it shows.
KEPT = ("REPORT.md", "tables/*.csv", "tables/*.md", "tables/*.json", "figures/*.png")
#: The run's record of its stages, one JSON object a line (:func:`log_stage`).
RUN_LOG = "runs.jsonl"


def code_commit() -> str | None:
    """The git commit of the checkout kpstudy runs from, with ``+changes`` when its
    ``kpstudy``, ``data_gen`` or ``notebooks`` differ from it; ``None`` outside a git
    checkout (an installed copy) or without git."""
    root = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True
        )
        if head.returncode:
            return None
        changes = subprocess.run(
            [
                "git",
                "-C",
                str(root),
                "status",
                "--porcelain",
                "--",
                "kpstudy",
                "data_gen",
                "notebooks",
            ],
            capture_output=True,
            text=True,
        )
    except OSError:
        return None
    return head.stdout.strip() + ("+changes" if changes.stdout.strip() else "")


def log_stage(run, stage: str, seconds: float, *, finished: bool, command=None) -> dict:
    """Add a stage's line to ``run/runs.jsonl`` (rewritten atomically) and return it:
    ``stage``, ``seconds`` (wall), ``finished`` (False: interrupted or failed), ``at`` (UTC,
    ISO 8601), ``commit`` (:func:`code_commit`), ``code``
    (:func:`kpstudy.io.source_fingerprint`) and ``command`` (None when not given)."""
    from kpstudy.io import source_fingerprint, write_text_atomic

    entry = dict(
        stage=stage,
        seconds=round(float(seconds), 1),
        finished=bool(finished),
        at=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        commit=code_commit(),
        code=source_fingerprint(),
        command=command,
    )
    path = Path(run) / RUN_LOG
    old = path.read_text() if path.is_file() else ""
    write_text_atomic(path, old + json.dumps(entry) + "\n")
    return entry


def run_log(run) -> list[dict]:
    """The lines of ``run/runs.jsonl`` in order (``[]`` without the file)."""
    path = Path(run) / RUN_LOG
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def publish(run, dest, *, commit: str | None = None, command: str | None = None) -> Path:
    """Copy the run ``run`` (a ``results/<profile>`` folder with ``REPORT.md``) into
    ``dest`` and write ``dest/STAMP.md``.

    ``commit`` is the git commit of the code that ran (7–40 hex digits), ``command`` the
    command line that ran it; either left out is taken from the run's ``runs.jsonl``
    (:func:`log_stage`) when every stage there names the same one. The stamp lists both,
    this machine (cores, processor, torch), the stages' seconds summed over the run's
    invocations (from ``runs.jsonl``) and each notebook's last execution in seconds
    (papermill's record; a campaign resumed from its store shows only its last part: the
    report's cost table sums every instance). ``dest`` is replaced whole, atomically.
    Returns ``dest``.

    Raises ``ValueError`` naming the argument for a run without a report or tables, a
    commit that is not hex (or none given nor recorded), or an empty command.
    """
    from kpstudy.io import check_writable, staged_directory, write_text_atomic

    run, dest = Path(run), Path(dest)
    if not (run / "REPORT.md").is_file() or not list(run.glob("tables/*.csv")):
        raise ValueError(
            f"run: expected a results folder with REPORT.md and tables/*.csv, got {str(run)!r}"
        )
    recorded = run_log(run)
    if commit is None:
        commit = _the_one(recorded, "commit")
    if command is None:
        command = _the_one(recorded, "command")
    if commit is None or not re.fullmatch(r"[0-9a-f]{7,40}", commit):
        raise ValueError(f"commit: expected 7 to 40 hex digits (git rev-parse), got {commit!r}")
    if command is None or not command.strip():
        raise ValueError(f"command: expected the command line that made the run, got {command!r}")
    check_writable(dest, "dest")
    files = sorted({p for pattern in KEPT for p in run.glob(pattern)})
    with staged_directory(dest, {"run": str(run.resolve()), "commit": commit}) as (staging, _):
        for source in files:
            target = staging / source.relative_to(run)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
        write_text_atomic(staging / "STAMP.md", stamp_markdown(run, commit, command))
    return dest


def _the_one(entries: list[dict], key: str):
    """The value every entry gives ``key``, where there is exactly one; else None."""
    values = {entry.get(key) for entry in entries}
    return values.pop() if len(values) == 1 else None


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
    stages: dict[str, list] = {}
    for entry in run_log(run):
        stages.setdefault(entry["stage"], []).append(entry)
    lines = [
        "# What made this result",
        "",
        f"- commit: `{commit}`",
        f"- command: `{command}`",
        f"- machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}, torch {torch.__version__}",
        "",
    ]
    if stages:
        lines += [
            "| stage | seconds (every invocation) | invocations | finished | commits |",
            "|---|---|---|---|---|",
            *(
                f"| {stage} | {sum(e['seconds'] for e in entries):.0f} | {len(entries)} | "
                f"{sum(e['finished'] for e in entries)} | "
                + ", ".join(sorted({f"`{e['commit']}`" for e in entries}))
                + " |"
                for stage, entries in stages.items()
            ),
            f"| total | {sum(e['seconds'] for es in stages.values() for e in es):.0f} | | | |",
            "",
        ]
    lines += [
        "| notebook | seconds (last execution) |",
        "|---|---|",
        *(f"| {name} | {value:.0f} |" for name, value in seconds.items()),
        f"| total | {sum(seconds.values()):.0f} |",
        "",
    ]
    return "\n".join(lines)
