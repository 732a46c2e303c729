"""Atomic result files: write to a temporary file beside the target, then rename.

A reader never sees a partial file, and an interrupted run leaves the old file intact.
:func:`source_fingerprint` names the code that computed a result, so that results of
other code are not reused.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import hashlib
import importlib
import os
import secrets
from pathlib import Path

import pandas as pd


@functools.cache
def source_fingerprint(packages: tuple[str, ...] = ("kpstudy", "data_gen")) -> str:
    """12 hex digits of SHA-256 over the code of ``packages`` (their ``.py`` files), with
    docstrings and comments left out: an edit to the documentation keeps results current,
    any other edit does not. Computed once per process."""
    digest = hashlib.sha256()
    for package in packages:
        digest.update(tree_fingerprint(Path(importlib.import_module(package).__file__).parent))
    return digest.hexdigest()[:12]


def tree_fingerprint(root) -> bytes:
    """SHA-256 over the syntax trees of the ``.py`` files under ``root`` (relative paths
    included), docstrings and comments left out."""
    root = Path(root)
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (
                isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(ast.dump(tree).encode())
    return digest.digest()


#: Names of the temporary files of :func:`atomic_path`: ``.<target name>.<8 hex>.tmp``.
TEMPORARY_GLOB = ".*.tmp"


@contextlib.contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` (parent folders created) to write to; moved onto
    ``path`` when the block succeeds, removed when it fails.

    The temporary file is created with mode ``0o666`` less the umask, like any other file
    (not ``tempfile.mkstemp``'s 0600), so that the finished file has the usual permissions.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:  # a name in use (odds 2⁻³² each): draw another
            continue
    try:
        yield str(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def remove_temporary_files(root) -> list[Path]:
    """Delete the temporary files that killed atomic writes left under ``root`` (every
    depth); return their paths."""
    stale = [p for p in Path(root).rglob(TEMPORARY_GLOB) if p.is_file()]
    for p in stale:
        p.unlink()
    return stale


def write_text_atomic(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (creating parent folders)."""
    return write_bytes_atomic(path, text.encode())


def write_bytes_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (creating parent folders)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    return Path(path)


def write_table(df: pd.DataFrame, stem) -> tuple[Path, Path]:
    """Write ``df`` as ``stem.csv`` and ``stem.md`` (GitHub Markdown), each atomically."""
    stem = Path(stem)
    csv = write_text_atomic(stem.with_suffix(".csv"), df.to_csv(index=False))
    md = write_text_atomic(stem.with_suffix(".md"), _markdown(df) + "\n")
    return csv, md


def save_figure(fig, path, dpi: int = 130) -> Path:
    """Save a matplotlib figure as PNG at ``path`` atomically, then close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return Path(path)


def _markdown(df: pd.DataFrame) -> str:
    def fmt(x):
        if x is None or x is pd.NA or (isinstance(x, float) and x != x):
            return "–"
        if isinstance(x, float):
            return f"{x:.6g}"
        return str(x)

    head = "| " + " | ".join(map(str, df.columns)) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    rows = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *rows])


def check_output_dir(out, overwrite: bool, name: str = "out") -> Path:
    """Refuse an output folder that is not empty (unless ``overwrite``) or not writable.

    Raises ``FileExistsError`` / ``PermissionError`` / ``NotADirectoryError`` naming
    ``name`` before anything is written.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{name}: {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{name}: directory {out} is not empty; pass --overwrite to replace")
    return check_writable(out, name)


def check_writable(folder, name: str = "out") -> Path:
    """Refuse a folder that can neither be written into nor created.

    ``folder`` itself, or where it does not exist its nearest existing ancestor, must be a
    directory this process may write into (a read-only file system counts as not
    writable). Raises ``NotADirectoryError`` / ``PermissionError`` naming ``name``;
    returns ``Path(folder)``. Nothing is created.
    """
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise NotADirectoryError(
            f"{name}: cannot write into {existing} (not a directory); expected a writable "
            f"folder for {folder}"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(
            f"{name}: cannot write into {existing} (read-only); expected a writable folder "
            f"for {folder}"
        )
    return folder


def check_output_file(path, name: str = "out") -> Path:
    """Refuse an output file path that is a folder or whose folder is not writable (see
    :func:`check_writable`), before any work: ``IsADirectoryError`` / ``NotADirectoryError``
    / ``PermissionError`` naming ``name``. Returns ``Path(path)``."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{name}: expected a file path, got the folder {path}")
    check_writable(path.parent, name)
    return path


@contextlib.contextmanager
def staged_directory(out, config: dict):
    """Build a folder beside ``out`` and move it onto ``out`` when the block succeeds.

    Yields ``(staging, resumed)``. The staging folder ``.<name>.partial`` keeps
    ``config`` in ``.config.json``: a later run with the same config resumes in it (the
    caller skips what is already there), another config starts afresh. On failure the
    staging folder stays for a resume and ``out`` is untouched. The temporary files of
    atomic writes that a killed run left in the staging folder are not carried into ``out``.
    """
    import json
    import shutil

    out = Path(out)
    staging = out.parent / f".{out.name}.partial"
    stamp = staging / ".config.json"
    text = json.dumps(config, sort_keys=True)
    resumed = stamp.exists() and stamp.read_text() == text
    if staging.exists() and not resumed:
        shutil.rmtree(staging)
    staging.mkdir(parents=True, exist_ok=True)
    write_text_atomic(stamp, text)
    yield staging, resumed
    stamp.unlink()
    remove_temporary_files(staging)  # of writes killed in an earlier, interrupted run
    if out.exists():
        shutil.rmtree(out)
    os.replace(staging, out)
