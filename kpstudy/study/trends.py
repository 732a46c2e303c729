"""The study's statistics: a verified rate's 95 % interval, and the trends the paper
states (paper §8.3–8.4) judged at 95 % on a table's numbers.

**Intervals.** :func:`rate_interval` is the Wilson score interval of ``k`` successes in
``n`` trials (``scipy.stats.binomtest(k, n).proportion_ci(method='wilson')``): its
coverage stays near the nominal 95 % from a handful of seeds to thousands, and it is
never empty or degenerate at ``k = 0`` or ``k = n`` (0/10 → [0, 0.278]), where the normal
approximation collapses to a point; the exact Clopper–Pearson interval guarantees 95 %
but is wider than needed (0/10 → [0, 0.308]). The paper's rates get the interval of
:data:`PAPER_SEEDS` seeds (:func:`paper_interval`): it does not say how many of its 200
seeds had their pose inside Ξ (the rate's denominator), so its intervals are if anything
too narrow.

**Trends.** A *statement* says how a quantity moves along one axis of a table, the other
axes held fixed: "the verified rate rises with α", "the time falls with α", "overlapping
hulls cost more", "soundness rises with κ" (:data:`STATEMENTS`). :func:`trend` pairs the
cells that differ only in that axis (its smallest value against its largest), counts the
pairs that move along the statement, against it, or not at all, and tests the difference
between the two ends at 95 %, pooled over the pairs:

* a proportion (verified rate, soundness, completeness): the successes among the trials
  of the pairs' smallest-axis cells against those of their largest-axis cells, by the
  two-sided Fisher exact test (``scipy.stats.fisher_exact``; exact at any count, 0 and
  ``n`` included). The same seeds recur in both cells of a pair and the test takes the
  two ends as independent samples, which makes it conservative for a rate; T-prob's
  Monte Carlo samples cluster by image, which makes it too confident there.
* a time per instance (the paper states means, and its standard deviations exceed them):
  Welch's t-test (``scipy.stats.ttest_ind_from_stats``, unequal variances) between the
  union of the instances at each end, whose mean and standard deviation follow exactly
  from each cell's count, mean and standard deviation; the paper's times are tested the
  same way, from its means and standard deviations over 200 instances. The tables keep
  no per-instance times, so no rank test.

:func:`verdict` says *shown* (significant in the paper's direction), *contradicted*
(significant against it) or *not shown*; a test whose cells have fewer than
:data:`MIN_SEEDS` seeds (instances for a time) is a smoke test, and :func:`describe` says
so beside the verdict: the verdict is computed, never a finding. :func:`trend_table`
tests every statement for the paper's numbers and, on the same pairs, for ours. Nothing
here is written by hand: a sentence says what the numbers say.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy import stats

__all__ = [
    "LEVEL",
    "MIN_SEEDS",
    "PAPER_SEEDS",
    "STATEMENTS",
    "Statement",
    "Trend",
    "describe",
    "paper_interval",
    "rate_interval",
    "rate_intervals",
    "trend",
    "trend_table",
    "verdict",
]

#: Confidence level of every interval and test.
LEVEL = 0.95
#: Seeds per cell below which a cell is a smoke test, not a finding.
MIN_SEEDS = 20
#: Seeds per cell of the paper's verification tables (paper §8.4).
PAPER_SEEDS = 200
#: The paper's Monte Carlo samples per T-prob cell: 3000 images × 5000 (paper §8.3).
PAPER_SAMPLES = 3000 * 5000


def rate_interval(k, n, level: float = LEVEL) -> tuple[float, float]:
    """The Wilson score interval of a rate of ``k`` successes in ``n`` trials.

    Parameters
    ----------
    k, n : int
        Successes and trials, ``0 ≤ k ≤ n`` (a float that is an integer is accepted, as
        read back from a CSV).
    level : float
        Confidence level in (0, 1).

    Returns
    -------
    (float, float)
        ``(low, high)`` within [0, 1]; ``(nan, nan)`` when ``n`` is 0 or not a number.

    Examples
    --------
    >>> [round(v, 4) for v in rate_interval(0, 10)]
    [0.0, 0.2775]
    """
    if not 0 < level < 1:
        raise ValueError(f"level: expected a value in (0, 1), got {level!r}")
    if k is None or n is None or pd.isna(k) or pd.isna(n) or n == 0:
        return float("nan"), float("nan")
    if int(k) != k or int(n) != n or not 0 <= k <= n:
        raise ValueError(f"k, n: expected integers with 0 <= k <= n, got k={k!r}, n={n!r}")
    ci = stats.binomtest(int(k), int(n)).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


def rate_intervals(rates, n, level: float = LEVEL) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rate_interval` per element of ``rates`` (fractions) over ``n`` trials each
    (array-like or one number): ``k = rate · n`` rounded. Returns ``(low, high)`` arrays,
    NaN where the rate or ``n`` is NaN or ``n`` is 0."""
    rates = np.asarray(pd.to_numeric(pd.Series(np.ravel(rates)), errors="coerce"), np.float64)
    n = np.broadcast_to(np.asarray(n, np.float64), rates.shape)
    low, high = np.full(rates.shape, np.nan), np.full(rates.shape, np.nan)
    for i, (r, m) in enumerate(zip(rates, n)):
        if np.isfinite(r) and np.isfinite(m) and m > 0:
            low[i], high[i] = rate_interval(int(round(r * m)), int(m), level)
    return low, high


def paper_interval(rates, level: float = LEVEL) -> tuple[np.ndarray, np.ndarray]:
    """The intervals the paper's rates imply over its :data:`PAPER_SEEDS` seeds per cell
    (:func:`rate_intervals`)."""
    return rate_intervals(rates, PAPER_SEEDS, level)


@dataclass(frozen=True)
class Statement:
    """A trend the paper states: ``value`` moves with ``sign`` (+1 rises, −1 falls) as
    ``axis`` goes from its smallest to its largest value; ``paper`` names the paper's
    column of the same quantity (None: the paper's numbers are not compared);
    ``relative``: changes within 5 % of the smaller value count as flat when the pairs
    are counted (times).

    ``count``: our column of each cell's trials (seeds inside Ξ of a rate, instances of a
    time); ``paper_count``: the paper's, one number per cell. ``spread``: our column of a
    time's standard deviation over the cell's instances (``ddof = 0``) and
    ``paper_spread`` the paper's (``ddof = 1``); None for a proportion."""

    text: str
    value: str
    axis: str
    sign: int
    paper: str | None = None
    relative: bool = False
    count: str | None = None
    paper_count: float | None = None
    spread: str | None = None
    paper_spread: str | None = None


def _rate(text: str, axis: str, sign: int) -> Statement:
    return Statement(text, "rate", axis, sign, "paper_rate", False, "seeds_inside", PAPER_SEEDS)


def _time(text: str, axis: str, sign: int) -> Statement:
    return Statement(
        text, "time_all", axis, sign, "paper_time_mean", True, "timed", PAPER_SEEDS,
        "time_std", "paper_time_std",
    )  # fmt: skip


def _prob(text: str, value: str, axis: str, sign: int) -> Statement:
    return Statement(text, value, axis, sign, f"paper_{value}", False, "samples", PAPER_SAMPLES)


#: The paper's statements, on :func:`kpstudy.study.comparison.method_cells` columns (``rate``,
#: ``time_all``) and on a T-prob table's (``soundness``, ``completeness``).
STATEMENTS = (
    _rate("Verified rate rises with α", "alpha", +1),
    _rate("Verified rate falls with κ", "kappa", -1),
    _time("Time per instance falls with α", "alpha", -1),
    _time("Time per instance rises with κ", "kappa", +1),
    _time("Time per instance rises with m", "m", +1),
    _time("Overlapping hulls cost more time", "overlapping", +1),
    _time("Larger brightness / contrast changes cost more time", "level", +1),
    _prob("Soundness rises with κ", "soundness", "kappa", +1),
    _prob("Soundness falls with α", "soundness", "alpha", -1),
    _prob("Completeness falls with κ", "completeness", "kappa", -1),
)

#: Relative change below which a time counts as unchanged.
_RELATIVE_FLAT = 0.05


@dataclass(frozen=True)
class Trend:
    """Counts of cell pairs (smallest against largest value of the axis, every other key
    equal): ``along`` the statement, ``against`` it, ``flat``; ``mean_change`` is the mean
    of (largest − smallest) over the pairs (NaN without any).

    The test pooled over the pairs: ``difference`` (largest − smallest end: of the
    pooled proportions, or of the pooled mean times), ``p_value`` (two-sided; NaN when
    not tested: no counts, or too few to test), ``smallest`` (the fewest trials of a
    cell in the pairs; NaN without counts); ``sign`` is the statement's."""

    pairs: int
    along: int
    against: int
    flat: int
    mean_change: float
    difference: float = float("nan")
    p_value: float = float("nan")
    smallest: float = float("nan")
    sign: int = 1


def trend(
    frame: pd.DataFrame,
    value: str,
    axis: str,
    keys: list[str],
    sign: int,
    relative: bool = False,
    count=None,
    spread: str | None = None,
    ddof: int = 0,
) -> Trend:
    """Count and test the pairs of ``frame``'s rows that differ only in ``axis``: per
    value of ``keys``, the row at the smallest ``axis`` value against the row at the
    largest.

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
    count : str or float, optional
        Each cell's trials: a column of ``frame`` or one number for every cell. Without
        it, nothing is tested (``p_value`` NaN).
    spread : str, optional
        A column of each cell's standard deviation of ``value`` (a mean): Welch's t-test
        on the pooled instances. Without it ``value`` is a proportion of ``count``
        trials: Fisher's exact test on the pooled counts (module docstring).
    ddof : {0, 1}
        The degrees of freedom ``spread`` was computed with (0: over the population).

    Returns
    -------
    Trend
        Pairs with a finite ``value`` at both ends only.
    """
    if sign not in (1, -1):
        raise ValueError(f"sign: expected +1 or -1, got {sign!r}")
    columns = [value, axis, *keys]
    columns += [c for c in (count, spread) if isinstance(c, str)]
    for name in columns:
        if name not in frame:
            raise ValueError(f"frame: expected a column {name!r}")
    changes, ends = [], ([], [])
    groups = frame.groupby(list(keys), sort=False, dropna=False) if keys else [((), frame)]
    for _, part in groups:
        part = part.dropna(subset=[axis])
        if part[axis].nunique() < 2:
            continue
        lo = part[part[axis] == part[axis].min()]
        hi = part[part[axis] == part[axis].max()]
        a, b = (float(pd.to_numeric(p[value], errors="coerce").mean()) for p in (lo, hi))
        if not (np.isfinite(a) and np.isfinite(b)):
            continue
        change = b - a
        flat_tol = _RELATIVE_FLAT * min(abs(a), abs(b)) if relative else 1e-9
        changes.append((change, abs(change) > flat_tol))
        for end, rows in zip(ends, (lo, hi)):
            end.append(rows)
    along = sum(bool(m and sign * c > 0) for c, m in changes)
    against = sum(bool(m and sign * c < 0) for c, m in changes)
    mean = float(np.mean([c for c, _ in changes])) if changes else float("nan")
    counts = Trend(len(changes), along, against, len(changes) - along - against, mean, sign=sign)
    if not changes or count is None:
        return counts
    lo, hi = (pd.concat(end) for end in ends)
    n_lo, n_hi = (_column(rows, count) for rows in (lo, hi))
    trials = np.concatenate([n_lo, n_hi])
    smallest = float(trials[np.isfinite(trials)].min()) if np.isfinite(trials).any() else np.nan
    x_lo, x_hi = (_column(rows, value) for rows in (lo, hi))
    if spread is None:
        difference, p = _proportions(x_lo, n_lo, x_hi, n_hi)
    else:
        s_lo, s_hi = (_column(rows, spread) for rows in (lo, hi))
        difference, p = _means((x_lo, s_lo, n_lo), (x_hi, s_hi, n_hi), ddof)
    return replace(counts, difference=difference, p_value=p, smallest=smallest)


def _column(rows: pd.DataFrame, column) -> np.ndarray:
    """``rows[column]`` as float64 (NaN where not a number), or ``column`` itself (a
    number) once per row."""
    if isinstance(column, str):
        return pd.to_numeric(rows[column], errors="coerce").to_numpy(np.float64)
    return np.full(len(rows), float(column))


def _proportions(x_lo, n_lo, x_hi, n_hi) -> tuple[float, float]:
    """The pooled difference of two ends' proportions ``x`` of ``n`` trials per cell, and
    the two-sided Fisher exact p-value; NaN without a trial at either end."""
    pooled = []
    for x, n in ((x_lo, n_lo), (x_hi, n_hi)):
        ok = np.isfinite(x) & np.isfinite(n) & (n > 0)
        pooled.append((int(np.rint(x[ok] * n[ok]).sum()), int(n[ok].sum())))
    (k_lo, m_lo), (k_hi, m_hi) = pooled
    if not (m_lo and m_hi):
        return float("nan"), float("nan")
    p = stats.fisher_exact([[k_hi, m_hi - k_hi], [k_lo, m_lo - k_lo]]).pvalue
    return k_hi / m_hi - k_lo / m_lo, float(p)


def _means(lo, hi, ddof: int) -> tuple[float, float]:
    """The difference of two ends' pooled means, each from its cells' (mean, standard
    deviation with ``ddof``, count), and Welch's two-sided p-value; NaN with fewer than
    two instances at either end."""
    pooled = []
    for mean, std, n in (lo, hi):
        ok = np.isfinite(mean) & np.isfinite(std) & np.isfinite(n) & (n > 0)
        mean, std, n = mean[ok], std[ok], n[ok]
        total = n.sum()
        if total < 2:
            return float("nan"), float("nan")
        centre = float((n * mean).sum() / total)
        # The union's sum of squares: within each cell, then between the cells' means.
        squares = ((n - ddof) * std**2).sum() + (n * (mean - centre) ** 2).sum()
        pooled.append((centre, float(np.sqrt(squares / (total - 1))), float(total)))
    (m_lo, s_lo, n_lo), (m_hi, s_hi, n_hi) = pooled
    difference = m_hi - m_lo
    if difference == 0:
        return 0.0, 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        p = stats.ttest_ind_from_stats(m_hi, s_hi, n_hi, m_lo, s_lo, n_lo, equal_var=False).pvalue
    return difference, float(p)


def verdict(t: Trend, level: float = LEVEL) -> str:
    """``'shown'`` (the two ends differ at ``level`` in the statement's direction),
    ``'contradicted'`` (they differ against it), ``'not shown'`` (no significant
    difference), ``'cannot tell'`` (no pair, or nothing to test: no counts)."""
    if t.pairs == 0 or not np.isfinite(t.p_value):
        return "cannot tell"
    if t.p_value < 1 - level:
        return "shown" if t.sign * t.difference > 0 else "contradicted"
    return "not shown"


def describe(t: Trend, unit: str = "rate") -> str:
    """A short account of ``t``: the verdict and its p-value, a smoke-test warning when a
    cell has fewer than :data:`MIN_SEEDS` trials, how many pairs of how many moved as
    stated (and how many against, how many not at all) and the mean change (``unit``
    ``'rate'``: in percentage points, else seconds)."""
    if t.pairs == 0:
        return "cannot tell: no pair"
    counts = f"{t.along} of {t.pairs}"
    if t.against:
        counts += f", {t.against} against"
    if t.flat:
        counts += f", {t.flat} unchanged"
    notes = []
    if np.isfinite(t.p_value):
        notes.append("p < 0.001" if t.p_value < 0.001 else f"p = {t.p_value:.2g}")
    elif np.isnan(t.smallest):
        notes.append("no counts to test")
    else:
        notes.append("too few to test")
    if np.isfinite(t.smallest) and t.smallest < MIN_SEEDS:
        notes.append(f"smoke test, {t.smallest:.0f} per cell")
    return f"{verdict(t)} ({'; '.join(notes)}): {counts} ({_change(t.mean_change, unit)})"


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
        (``–`` where the paper has no such column). A statement whose count or spread
        column ``cells`` lacks is counted, not tested. No rows without any such statement.
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
            spread = s.paper_spread if s.paper_spread in cells else None
            testable = s.paper_spread is None or spread is not None
            t = trend(
                groups[0][1], s.paper, s.axis, others, s.sign, s.relative,
                s.paper_count if testable else None, spread, ddof=1,
            )  # fmt: skip
            table.loc[s.text, paper] = describe(t, unit)
        testable = s.count in cells and (s.spread is None or s.spread in cells)
        for name, (_, part) in zip(names, groups):
            t = trend(
                part, s.value, s.axis, others, s.sign, s.relative,
                s.count if testable else None, s.spread if testable else None,
            )  # fmt: skip
            table.loc[s.text, name] = describe(t, unit)
    return table.fillna("–")
