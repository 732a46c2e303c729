"""The trends the paper states (paper §8.3–8.4), tested on a table's numbers.

A *statement* says how a quantity moves along one axis of a table, the other axes held
fixed: "the verified rate rises with α", "the time falls with α", "overlapping hulls cost
more", "soundness rises with κ" (:data:`STATEMENTS`). :func:`trend` pairs the cells that
differ only in that axis (its smallest value against its largest) and counts the pairs
that move along the statement, against it, or not at all; :func:`verdict` turns the
counts into a word and :func:`statement_lines` into one sentence per statement, for ours
and, on the same pairs, for the paper's numbers. Nothing here is written by hand: a
sentence says what the counts say.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["STATEMENTS", "Statement", "Trend", "statement_lines", "trend", "verdict"]


@dataclass(frozen=True)
class Statement:
    """A trend the paper states: ``value`` moves with ``sign`` (+1 rises, −1 falls) as
    ``axis`` goes from its smallest to its largest value; ``paper`` names the paper's
    column of the same quantity (None: the paper's numbers are not compared);
    ``relative``: changes within 5 % of the smaller value count as flat (times)."""

    text: str
    value: str
    axis: str
    sign: int
    paper: str | None = None
    relative: bool = False


#: The paper's statements, on :func:`kpstudy.comparison.method_cells` columns (``rate``,
#: ``time_all``) and on a T-prob table's (``soundness``).
STATEMENTS = (
    Statement("Verified rate rises with α", "rate", "alpha", +1, "paper_rate"),
    Statement("Verified rate falls with κ", "rate", "kappa", -1, "paper_rate"),
    Statement("Time per instance falls with α", "time_all", "alpha", -1, "paper_time_mean", True),
    Statement(
        "Overlapping hulls cost more time", "time_all", "overlapping", +1, "paper_time_mean", True
    ),
    Statement("Soundness rises with κ", "soundness", "kappa", +1, "paper_soundness"),
)

#: Relative change below which a time counts as unchanged.
_RELATIVE_FLAT = 0.05


@dataclass(frozen=True)
class Trend:
    """Counts of cell pairs (smallest against largest value of the axis, every other key
    equal): ``along`` the statement, ``against`` it, ``flat``; ``mean_change`` is the mean
    of (largest − smallest) over the pairs (NaN without any)."""

    pairs: int
    along: int
    against: int
    flat: int
    mean_change: float


def trend(
    frame: pd.DataFrame,
    value: str,
    axis: str,
    keys: list[str],
    sign: int,
    relative: bool = False,
) -> Trend:
    """Count the pairs of ``frame``'s rows that differ only in ``axis``.

    Parameters
    ----------
    frame : DataFrame
        One row per cell of one series (one model and method), with columns ``keys``,
        ``axis`` and ``value``.
    value : str
        The quantity (e.g. ``'rate'``, dimensionless; ``'time_all'``, seconds).
    axis : str
        The column the statement is about (``'alpha'``, ``'kappa'``, ``'overlapping'``).
    keys : list of str
        The other columns that name a cell; a pair has them all equal.
    sign : {+1, -1}
        +1: ``value`` should rise from the smallest to the largest ``axis`` value.
    relative : bool
        Count a change below 5 % of the smaller value as flat (for times).

    Returns
    -------
    Trend
        Pairs with a finite ``value`` at both ends only.
    """
    if sign not in (1, -1):
        raise ValueError(f"sign: expected +1 or -1, got {sign!r}")
    for name in (value, axis, *keys):
        if name not in frame:
            raise ValueError(f"frame: expected a column {name!r}")
    values = sorted(frame[axis].dropna().unique())
    changes = []
    if len(values) >= 2:
        lo = frame[frame[axis] == values[0]]
        hi = frame[frame[axis] == values[-1]]
        cols = list(keys)
        merged = (
            lo[[*cols, value]].merge(hi[[*cols, value]], on=cols, suffixes=("_lo", "_hi"))
            if cols
            else pd.DataFrame({f"{value}_lo": lo[value].to_numpy()[:1],
                               f"{value}_hi": hi[value].to_numpy()[:1]})
        )  # fmt: skip
        a = pd.to_numeric(merged[f"{value}_lo"], errors="coerce").to_numpy(np.float64)
        b = pd.to_numeric(merged[f"{value}_hi"], errors="coerce").to_numpy(np.float64)
        ok = np.isfinite(a) & np.isfinite(b)
        a, b = a[ok], b[ok]
        change = b - a
        flat_tol = _RELATIVE_FLAT * np.minimum(np.abs(a), np.abs(b)) if relative else 1e-9
        moved = np.abs(change) > flat_tol
        changes = [(c, m) for c, m in zip(change, moved)]
    along = sum(bool(m and sign * c > 0) for c, m in changes)
    against = sum(bool(m and sign * c < 0) for c, m in changes)
    mean = float(np.mean([c for c, _ in changes])) if changes else float("nan")
    return Trend(len(changes), along, against, len(changes) - along - against, mean)


def verdict(t: Trend) -> str:
    """``'yes'`` (some pairs along, none against), ``'mostly'`` (more along than against),
    ``'no'`` (as many or more against, or all flat), ``'cannot tell'`` (no pair)."""
    if t.pairs == 0:
        return "cannot tell"
    if t.along and not t.against:
        return "yes"
    if t.along > t.against:
        return "mostly"
    return "no"


def _describe(t: Trend, unit: str) -> str:
    if t.pairs == 0:
        return "cannot tell (no pair of cells differing only in this axis)"
    change = f"{t.mean_change:+.0%}" if unit == "rate" else f"{t.mean_change:+.3g} s"
    return (
        f"{verdict(t)} ({t.along} of {t.pairs} pairs along, {t.against} against, "
        f"{t.flat} unchanged; mean change {change})"
    )


def statement_lines(
    cells: pd.DataFrame,
    keys: list[str],
    series: list[str],
    statements=STATEMENTS,
) -> list[str]:
    """One sentence per statement whose axis and value ``cells`` has (and whose axis
    takes two values or more): the paper's verdict on the same pairs, then ours per
    series.

    Parameters
    ----------
    cells : DataFrame
        One row per series and cell (e.g. :func:`kpstudy.comparison.method_cells`).
    keys : list of str
        The columns that name a cell (the statement's axis among them).
    series : list of str
        The columns that name a series (e.g. ``['model', 'method']``); each is tested
        apart.
    """
    lines = []
    for s in statements:
        if s.axis not in keys or s.value not in cells or cells[s.axis].nunique() < 2:
            continue
        others = [k for k in keys if k != s.axis]
        unit = "rate" if not s.relative else "time"
        groups = list(cells.groupby(series, sort=False)) if series else [((), cells)]
        parts = []
        for name, part in groups:
            name = name if isinstance(name, tuple) else (name,)
            label = " ".join(str(n) for n in name if str(n)) or "ours"
            t = trend(part, s.value, s.axis, others, s.sign, s.relative)
            parts.append(f"{label}: {_describe(t, unit)}")
        paper = ""
        if s.paper and s.paper in cells and groups:
            first = groups[0][1]
            t = trend(first, s.paper, s.axis, others, s.sign, s.relative)
            paper = f" The paper's numbers on the same cells: {_describe(t, unit)}."
        lines.append(f"*{s.text}* (the paper's statement).{paper} Ours: " + "; ".join(parts) + ".")
    return lines
