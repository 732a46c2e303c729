"""Atomic result files: write to a temporary file beside the target, then rename.

A reader never sees a partial file, and an interrupted run leaves the old file intact.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import pandas as pd


@contextlib.contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` (parent folders created) to write to; moved onto
    ``path`` when the block succeeds, removed when it fails."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def write_text_atomic(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (creating parent folders)."""
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    return Path(path)


def write_table(df: pd.DataFrame, stem) -> tuple[Path, Path]:
    """Write ``df`` as ``stem.csv`` and ``stem.md`` (GitHub Markdown), each atomically."""
    stem = Path(stem)
    csv = write_text_atomic(stem.with_suffix(".csv"), df.to_csv(index=False))
    md = write_text_atomic(stem.with_suffix(".md"), _markdown(df) + "\n")
    return csv, md


def _markdown(df: pd.DataFrame) -> str:
    def fmt(x):
        if isinstance(x, float):
            return f"{x:.6g}"
        return str(x)

    head = "| " + " | ".join(map(str, df.columns)) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    rows = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *rows])
