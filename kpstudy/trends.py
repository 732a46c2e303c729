"""The trends the paper states (paper §8.3–8.4), tested on a table's numbers.

A *statement* says how a quantity moves along one axis of a table, the other axes held
fixed: "the verified rate rises with α", "the time falls with α", "overlapping hulls cost
more", "soundness rises with κ" (:data:`STATEMENTS`). :func:`trend` pairs the cells that
differ only in that axis (its smallest value against its largest) and counts the pairs
that move along the statement, against it, or not at all; :func:`verdict` turns the
counts into a word, and :func:`trend_table` tests every statement for the paper's
numbers and, on the same pairs, for ours. Nothing here is written by hand: a
sentence says what the counts say.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["STATEMENTS", "Statement", "Trend", "describe", "trend", "trend_table", "verdict"]


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


def describe(t: Trend, unit: str = "rate") -> str:
    """A short account of ``t``: the verdict, how many pairs of how many moved as stated
    (and how many against, how many not at all) and the mean change (``unit``
    ``'rate'``: in percentage points, else seconds)."""
    if t.pairs == 0:
        return "cannot tell: no pair"
    counts = f"{t.along} of {t.pairs}"
    if t.against:
        counts += f", {t.against} against"
    if t.flat:
        counts += f", {t.flat} unchanged"
    return f"{verdict(t)}: {counts} ({_change(t.mean_change, unit)})"


def _change(value: float, unit: str) -> str:
    """A mean change: a rate in percentage points (2 significant digits below 10), a
    time in seconds."""
    if unit != "rate":
        return f"{value:+.3g} s"
    points = 100 * value
    return f"{points:+.0f} pp" if abs(points) >= 10 else f"{points:+.2g} pp"


def trend_table(
    cells: pd.DataFrame,
    keys: list[str],
    series: list[str],
    statements=STATEMENTS,
    label=None,
) -> pd.DataFrame:
    """Each statement the cells can test, for the paper's numbers and for ours per series.

    Parameters
    ----------
    cells : DataFrame
        One row per series and cell (e.g. :func:`kpstudy.comparison.method_cells`).
    keys : list of str
        The columns that name a cell (a statement's axis among them).
    series : list of str
        The columns that name a series (e.g. ``['model', 'method']``), each tested apart;
        empty: one series.
    label : callable, optional
        ``label(values) -> str``: a series' row label from its tuple of ``series`` values.

    Returns
    -------
    DataFrame
        Index: ``"the paper's numbers"`` (on the first series' cells) then one label per
        series (``label(values)`` of its ``series`` values; by default joined by spaces,
        ``"ours"`` without any);
        columns: the statements whose axis is in ``keys`` with two values or more and
        whose value column ``cells`` has; entries: :func:`describe`. Empty without any
        such statement.
    """
    usable = [
        s
        for s in statements
        if s.axis in keys and s.value in cells and cells[s.axis].nunique() >= 2
    ]
    groups = list(cells.groupby(series, sort=False)) if series else [((), cells)]
    labels = []
    for name, _ in groups:
        name = name if isinstance(name, tuple) else (name,)
        labels.append(label(name) if label else " ".join(str(n) for n in name if str(n)) or "ours")
    paper_row = "the paper's numbers"
    table = pd.DataFrame(index=[paper_row, *labels], columns=[s.text for s in usable], dtype=object)
    for s in usable:
        others = [k for k in keys if k != s.axis]
        unit = "time" if s.relative else "rate"
        if s.paper and s.paper in cells and groups:
            t = trend(groups[0][1], s.paper, s.axis, others, s.sign, s.relative)
            table.loc[paper_row, s.text] = describe(t, unit)
        for label, (_, part) in zip(labels, groups):
            t = trend(part, s.value, s.axis, others, s.sign, s.relative)
            table.loc[label, s.text] = describe(t, unit)
    return table.fillna("–")
