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


#: The paper's statements, on :func:`kpstudy.study.comparison.method_cells` columns (``rate``,
#: ``time_all``) and on a T-prob table's (``soundness``).
STATEMENTS = (
    Statement("Verified rate rises with α", "rate", "alpha", +1, "paper_rate"),
    Statement("Verified rate falls with κ", "rate", "kappa", -1, "paper_rate"),
    Statement("Time per instance falls with α", "time_all", "alpha", -1, "paper_time_mean", True),
    Statement("Time per instance rises with κ", "time_all", "kappa", +1, "paper_time_mean", True),
    Statement("Time per instance rises with m", "time_all", "m", +1, "paper_time_mean", True),
    Statement(
        "Overlapping hulls cost more time", "time_all", "overlapping", +1, "paper_time_mean", True
    ),
    Statement(
        "Larger brightness / contrast changes cost more time",
        "time_all",
        "level",
        +1,
        "paper_time_mean",
        True,
    ),  # fmt: skip
    Statement("Soundness rises with κ", "soundness", "kappa", +1, "paper_soundness"),
    Statement("Soundness falls with α", "soundness", "alpha", -1, "paper_soundness"),
    Statement("Completeness falls with κ", "completeness", "kappa", -1, "paper_completeness"),
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
    """Count the pairs of ``frame``'s rows that differ only in ``axis``: per value of
    ``keys``, the row at the smallest ``axis`` value against the row at the largest.

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
    changes = []
    groups = frame.groupby(list(keys), sort=False, dropna=False) if keys else [((), frame)]
    for _, part in groups:
        part = part.dropna(subset=[axis])
        if part[axis].nunique() < 2:
            continue
        lo = part[part[axis] == part[axis].min()][value]
        hi = part[part[axis] == part[axis].max()][value]
        a, b = (float(pd.to_numeric(v, errors="coerce").mean()) for v in (lo, hi))
        if not (np.isfinite(a) and np.isfinite(b)):
            continue
        change = b - a
        flat_tol = _RELATIVE_FLAT * min(abs(a), abs(b)) if relative else 1e-9
        changes.append((change, abs(change) > flat_tol))
    along = sum(bool(m and sign * c > 0) for c, m in changes)
    against = sum(bool(m and sign * c < 0) for c, m in changes)
    mean = float(np.mean([c for c, _ in changes])) if changes else float("nan")
    return Trend(len(changes), along, against, len(changes) - along - against, mean)


def verdict(t: Trend) -> str:
    """``'yes'`` (more than half the pairs move as stated, none against), ``'partly'``
    (more along than against, otherwise), ``'no'`` (as many or more against, or none
    along), ``'cannot tell'`` (no pair)."""
    if t.pairs == 0:
        return "cannot tell"
    if not t.against and t.along > t.pairs / 2:
        return "yes"
    if t.along > t.against:
        return "partly"
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
        One row per series and cell (e.g. :func:`kpstudy.study.comparison.method_cells`).
    keys : list of str
        The columns that name a cell (a statement's axis among them).
    series : list of str
        The columns that name a series (e.g. ``['model', 'method']``), each tested apart;
        empty: one series.
    statements : sequence of Statement
    label : callable, optional
        ``label(values) -> str``: a series' column label from its tuple of ``series``
        values; by default the values joined by spaces (``"ours"`` without any).

    Returns
    -------
    DataFrame
        One row per statement whose axis is in ``keys`` with two values or more and whose
        value column ``cells`` has (index: its text); columns ``"the paper's numbers"``
        (on the first series' cells) and one per series; entries: :func:`describe`
        (``–`` where the paper has no such column). No rows without any such statement.
    """
    usable = [
        s
        for s in statements
        if s.axis in keys and s.value in cells and cells[s.axis].nunique() >= 2
    ]
    groups = list(cells.groupby(series, sort=False)) if series else [((), cells)]
    names = []
    for values, _ in groups:
        values = values if isinstance(values, tuple) else (values,)
        default = " ".join(str(v) for v in values if str(v)) or "ours"
        names.append(label(values) if label else default)
    paper = "the paper's numbers"
    table = pd.DataFrame(index=[s.text for s in usable], columns=[paper, *names], dtype=object)
    for s in usable:
        others = [k for k in keys if k != s.axis]
        unit = "time" if s.relative else "rate"
        if s.paper and s.paper in cells and groups:
            t = trend(groups[0][1], s.paper, s.axis, others, s.sign, s.relative)
            table.loc[s.text, paper] = describe(t, unit)
        for name, (_, part) in zip(names, groups):
            t = trend(part, s.value, s.axis, others, s.sign, s.relative)
            table.loc[s.text, name] = describe(t, unit)
    return table.fillna("–")
