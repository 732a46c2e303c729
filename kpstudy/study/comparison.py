"""The paper beside ours, one verification table at a time (T-local, T-global, T-resnet):
every method's verified rate and time per instance in one figure, and a compact table.

A *method* is one way the study decides an instance, read from the columns of a
:mod:`kpstudy.study.tables` table:

* ``alloc (heatmap)`` / ``alloc (paper)``: the allocation method (the paper's) under each
  tolerance reading (``tolerance_units``; plain ``alloc`` for tables without the column):
  ``verified_rate``, ``holds`` / ``violated`` / ``unknown`` / ``not_certifiable``,
  ``time_*``;
* ``pb``: the pose-bound method (:mod:`kpstudy.certify.pose_bound_method`), on the rows that
  have its columns (``pb_*``). Its time is one region search per hull, counted in full in each
  (κ, α) cell of the hull.

:func:`method_cells` turns a table into one row per model, method and cell (the data of
the figure, which a test can check); :func:`plot_comparison` draws it and
:func:`compact_table` condenses it to one row per model and method. Times compare like
with like: our mean time over proofs (``holds``) beside the paper's time per instance,
our refutations (``violated``, often a counterexample found in a fraction of a second)
apart; tables from before that split show the mean over all instances instead. Every
rate carries its 95 % Wilson interval (:func:`kpstudy.study.trends.rate_interval`; the
paper's over its 200 seeds), and the times their median and quartiles beside the mean. A
cell without data (no such record, or no seed inside Ξ for a rate) is hatched, never
drawn as 0.

:func:`time_caps` names, for ``kpstudy compare``
(:func:`kpstudy.study.reproduction.compare_results`), the cells of two runs' tables and
records where a time cap rather than a node budget ended a search: verdicts that depend on
the machine's speed, and so may explain a difference.
"""

from __future__ import annotations

import os

import numpy as np
import pandas as pd
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from kpstudy.study.tables import instance_label
from kpstudy.study.trends import MIN_SEEDS, PAPER_SEEDS, paper_interval, rate_intervals

__all__ = [
    "CONDITIONS",
    "GRID_COLUMNS",
    "PAPER_HARDWARE",
    "capped_searches",
    "compact_table",
    "method_cells",
    "plot_comparison",
    "save_comparison",
    "time_caps",
]

#: Table columns that name a row of a rate grid, in this order when present.
CONDITIONS = ("kind", "level", "m", "overlapping")
#: Table columns that name a column of a rate grid.
GRID_COLUMNS = ("kappa", "alpha")
#: The paper's hardware (ModelVerification.jl, paper §8).
PAPER_HARDWARE = "RTX A4000"
#: Columns of :func:`method_cells` besides the cell's own.
CELL_COLUMNS = (
    "instances",
    "seeds_inside",
    "holds",
    "violated",
    "unknown",
    "not_certifiable",
    "rate",
    "rate_lo",
    "rate_hi",
    "timed",
    "time_all",
    "time_std",
    "time_median",
    "time_q1",
    "time_q3",
    "time_proof",
    "time_refute",
    "time_unknown",
    "exact_holds",
    "paper_rate",
    "paper_rate_lo",
    "paper_rate_hi",
    "paper_time_mean",
    "paper_time_std",
)
_PAPER = ("paper_rate", "paper_time_mean", "paper_time_std")
#: method → {cell column: table column} (None: the method has none)
_ALLOC = dict(
    holds="holds", violated="violated", unknown="unknown", not_certifiable="not_certifiable",
    rate="verified_rate", time_all="time_mean", time_std="time_std", time_median="time_median",
    time_q1="time_q1", time_q3="time_q3", time_proof="time_holds_mean",
    time_refute="time_violated_mean", time_unknown="time_unknown_mean",
)  # fmt: skip
_PB = dict(
    holds="pb_holds", violated="pb_violated", unknown="pb_unknown", not_certifiable=None,
    rate="pb_verified_rate", time_all="pb_time_mean", time_std="pb_time_std",
    time_median="pb_time_median", time_q1="pb_time_q1", time_q3="pb_time_q3",
    time_proof="pb_time_holds_mean", time_refute="pb_time_violated_mean",
    time_unknown="pb_time_unknown_mean",
)  # fmt: skip
_NEEDED = ("kappa", "alpha", "instances", "seeds_inside", "verified_rate", *_PAPER)


def method_cells(table: pd.DataFrame) -> pd.DataFrame:
    """One row per model, method and cell of a T-local / T-global / T-resnet table.

    Parameters
    ----------
    table : DataFrame
        :func:`kpstudy.study.tables.t_local` (``t_global``, ``t_resnet``) output, as returned or
        read back from its CSV; columns a table of an older version lacks (``model``,
        ``tolerance_units``, ``pb_*``, ``time_holds_mean`` …) are taken as absent.

    Returns
    -------
    DataFrame
        Columns ``model`` (``''`` without one), ``method`` (``'alloc (heatmap)'``,
        ``'alloc (paper)'``, ``'alloc'``, ``'pb'``), the cell's :data:`CONDITIONS` present,
        ``kappa``, ``alpha``, then ``CELL_COLUMNS``: counts (``not_certifiable``: the
        allocation method's only, NaN for ``pb`` and tables without it), ``rate`` (holds
        among seeds inside Ξ ÷ those seeds, NaN without any; for ``pb``, seeds whose argmax
        → PnP pose is inside Ξ, ``pb_seeds_inside``, where the table has them) and its 95 %
        Wilson interval ``rate_lo`` – ``rate_hi`` (from the rate and ``seeds_inside``),
        ``timed`` (the instances a time is over: ``instances − errors``, for ``pb`` its
        verdicts), times in seconds per instance (``time_all`` over all instances, with
        ``time_std``, ``ddof = 0``, ``time_median``, ``time_q1``, ``time_q3``;
        ``time_proof`` over ``holds``, ``time_refute`` over ``violated``, ``time_unknown``
        over ``unknown``; NaN where there are none or the table has no such column),
        ``exact_holds`` (the pose-bound method's ``holds``
        decided by PnP over every region combination, exact for argmax → PnP; the others
        rest on the linearised bound; NaN for the allocation method), and
        the paper's rate with the interval of its 200 seeds and its time (NaN where the
        paper has no cell).
    """
    if not isinstance(table, pd.DataFrame):
        raise ValueError(f"table: expected a pandas DataFrame, got {type(table).__name__}")
    missing = [c for c in _NEEDED if c not in table]
    if missing:
        raise ValueError(f"table: expected a verification table with columns {missing}")
    conditions = [c for c in CONDITIONS if c in table]
    model = table["model"].astype(str) if "model" in table else pd.Series("", table.index)
    if "tolerance_units" in table:
        units = table["tolerance_units"].fillna("heatmap").astype(str)
        alloc_names = "alloc (" + units + ")"
    else:
        alloc_names = pd.Series("alloc", table.index)
    frames = [_method_frame(table, model, alloc_names, _ALLOC, conditions, None, "seeds_inside")]
    if "pb_holds" in table:
        rows = table["pb_holds"].notna()
        if rows.any():
            names = pd.Series("pb", table.index)
            frames.append(
                _method_frame(
                    table[rows],
                    model[rows],
                    names[rows],
                    _PB,
                    conditions,
                    "pb_enumeration_holds",
                    "pb_seeds_inside" if "pb_seeds_inside" in table else "seeds_inside",
                )  # fmt: skip
            )
    out = pd.concat(frames, ignore_index=True)
    order = {m: i for i, m in enumerate(_method_order(out["method"]))}
    out = out.sort_values(
        ["model", "method", *conditions, *GRID_COLUMNS],
        key=lambda s: s.map(order) if s.name == "method" else s,
        kind="stable",
    )
    return out.reset_index(drop=True)


def _method_frame(table, model, names, columns, conditions, exact, seeds) -> pd.DataFrame:
    values = {c: _numeric(table, t) for c, t in columns.items()}
    data = {"model": model.to_numpy(), "method": names.to_numpy()}
    for c in (*conditions, *GRID_COLUMNS):
        data[c] = table[c].to_numpy()
    values.update(
        instances=_numeric(table, "instances"),
        seeds_inside=_numeric(table, seeds),
        exact_holds=_numeric(table, exact),
        **{c: _numeric(table, c) for c in _PAPER},
    )
    values["rate_lo"], values["rate_hi"] = rate_intervals(values["rate"], values["seeds_inside"])
    values["paper_rate_lo"], values["paper_rate_hi"] = paper_interval(values["paper_rate"])
    if columns is _PB:  # the instances with a verdict of the pose-bound method
        values["timed"] = values["holds"] + values["violated"] + values["unknown"]
    else:  # errors have no time
        values["timed"] = values["instances"] - np.nan_to_num(_numeric(table, "errors"))
    data.update({c: values[c] for c in CELL_COLUMNS})
    return pd.DataFrame(data)


def _numeric(table: pd.DataFrame, column: str | None) -> np.ndarray:
    """``table[column]`` as float64, NaN where absent (or None) or not a number."""
    if column is None or column not in table:
        return np.full(len(table), np.nan)
    return pd.to_numeric(table[column], errors="coerce").to_numpy(np.float64)


def _method_order(methods: pd.Series) -> list[str]:
    """Allocation readings first ('heatmap' before 'paper'), then the pose-bound method."""
    rank = {"alloc (heatmap)": 0, "alloc": 0, "alloc (paper)": 1, "pb": 9}
    return sorted(methods.unique(), key=lambda m: (rank.get(m, 5), m))


def compact_table(table: pd.DataFrame) -> pd.DataFrame:
    """The numbers a reader compares, one row per model and method (paper §8.4 layout).

    Returns
    -------
    DataFrame
        ``model``, ``method``, ``instances``, ``holds``, ``violated``, ``unknown``,
        ``not_certifiable`` (counts over the table; None where the table has none),
        ``fewest_seeds`` (the fewest seeds inside Ξ of a cell: below
        :data:`kpstudy.study.trends.MIN_SEEDS` a smoke test), ``cells`` (cells where ours
        and the paper's rate both exist), ``rate`` (holds among the seeds inside Ξ over
        those cells ÷ those seeds) with its 95 % Wilson interval ``rate_lo`` – ``rate_hi``
        (the seeds recur from cell to cell and the interval takes them as independent:
        if anything too narrow), ``paper_rate`` (the mean of the paper's over those cells)
        with ``paper_rate_lo`` – ``paper_rate_hi`` (over 200 seeds per cell), ``delta``
        (``rate − paper_rate``), ``proof_s`` (mean seconds over our ``holds``),
        ``refutation_s`` (over our ``violated``), ``median_low_s`` – ``median_high_s`` (the
        smallest and the largest of the cells' median seconds over all instances; NaN for
        a table without medians), ``paper_s`` (the paper's mean time per instance,
        averaged over the method's cells that the paper has).
    """
    cells = method_cells(table)
    rows = []
    for (model, method), part in cells.groupby(["model", "method"], sort=False):
        both = part.dropna(subset=["rate", "paper_rate"])
        k = float(np.rint(both["rate"] * both["seeds_inside"]).sum())
        n = float(both["seeds_inside"].sum())
        rate = k / n if n else np.nan
        paper = float(both["paper_rate"].mean()) if len(both) else np.nan
        (rate_lo,), (rate_hi,) = rate_intervals([rate], n)
        (paper_lo,), (paper_hi,) = rate_intervals([paper], PAPER_SEEDS * len(both))
        seeds = part["seeds_inside"].dropna()
        medians = part["time_median"].dropna()
        rows.append(
            dict(
                model=model,
                method=method,
                instances=int(part["instances"].sum()),
                holds=_count(part["holds"]),
                violated=_count(part["violated"]),
                unknown=_count(part["unknown"]),
                not_certifiable=_count(part["not_certifiable"]),
                fewest_seeds=int(seeds.min()) if len(seeds) else None,
                cells=len(both),
                rate=rate,
                rate_lo=rate_lo,
                rate_hi=rate_hi,
                paper_rate=paper,
                paper_rate_lo=paper_lo,
                paper_rate_hi=paper_hi,
                delta=rate - paper,
                proof_s=_weighted(part["time_proof"], part["holds"]),
                refutation_s=_weighted(part["time_refute"], part["violated"]),
                median_low_s=float(medians.min()) if len(medians) else np.nan,
                median_high_s=float(medians.max()) if len(medians) else np.nan,
                paper_s=float(part["paper_time_mean"].mean()),
            )
        )
    return pd.DataFrame(rows)


def _count(values: pd.Series):
    """The sum of counts, or None where the table has none (an old table's column)."""
    return None if values.isna().all() else int(values.sum())


def _weighted(times: pd.Series, counts: pd.Series) -> float:
    """Pooled mean of per-cell means ``times`` over ``counts`` instances each."""
    ok = times.notna() & counts.notna() & (counts > 0)
    if not ok.any():
        return float("nan")
    return float((times[ok] * counts[ok]).sum() / counts[ok].sum())


def plot_comparison(table: pd.DataFrame, title: str, hardware: str | None = None) -> Figure:
    """Every method's verified rate and time per instance beside the paper's.

    Parameters
    ----------
    table : DataFrame
        A T-local / T-global / T-resnet table (see :func:`method_cells`).
    title : str
        The figure's title, e.g. ``"T-global: brightness and contrast"``.
    hardware : str, optional
        Where our times were measured, for the time panels' titles; default this
        machine's CPU count (``"2 CPU cores"``), right when the figure is drawn where the
        campaign ran.

    Returns
    -------
    matplotlib.figure.Figure
        Per model, a row of rate grids: one per method and the paper's, rows the cell's
        :data:`CONDITIONS` and columns (κ, α), one colour scale (0–1) for all; each of our
        cells reads our rate, the paper's and the difference, hatched where there is no
        rate. Below, per model, the time per instance on a log scale, cell by cell: per
        method the mean over proofs (filled), over refutations (hollow) and over unknowns
        (a cross: the budget spent), and the paper's mean ± std (black).
    """
    if not isinstance(title, str):
        raise ValueError(f"title: expected a string, got {type(title).__name__}")
    cells = method_cells(table)
    if cells.empty:
        raise ValueError("table: expected at least one row")
    hardware = hardware or f"{os.cpu_count()} CPU cores"
    conditions = [c for c in CONDITIONS if c in cells]
    rows = _keys(cells, conditions)
    cols = _keys(cells, list(GRID_COLUMNS))
    models = list(dict.fromkeys(cells["model"]))
    methods = _method_order(cells["method"])
    n_panels = len(methods) + 1
    panel_w = max(2.4, 1.0 * len(cols) + 0.9)
    panel_h = max(1.6, 0.55 * len(rows) + 0.9)
    width = max(9.0, panel_w * n_panels + 1.5)
    fig = Figure(figsize=(width, len(models) * (panel_h + 3.6) + 1.2), layout="constrained")
    grid = fig.add_gridspec(2 * len(models), n_panels, height_ratios=[panel_h, 3.0] * len(models))
    norm = Normalize(0.0, 1.0)
    image, legend = None, {}
    for i, model in enumerate(models):
        part = cells[cells["model"] == model]
        rate_axes = [fig.add_subplot(grid[2 * i, j]) for j in range(n_panels)]
        for j, method in enumerate(methods):
            mine = part[part["method"] == method]
            image = _rate_grid(rate_axes[j], mine, conditions, rows, cols, norm, ours=True)
            name = f"{model}: {method}" if model else method
            rate_axes[j].set_title(f"{name}\n{_counts(mine)}", fontsize="small")
            if method == "pb" and "pb_seeds_inside" in table:
                rate_axes[j].set_title(
                    rate_axes[j].get_title() + "\nrate among seeds whose argmax pose is in Ξ",
                    fontsize="small",
                )
        _rate_grid(rate_axes[-1], part, conditions, rows, cols, norm, ours=False)
        rate_axes[-1].set_title(f"paper ({PAPER_HARDWARE})\nverified rate", fontsize="small")
        for ax in rate_axes[1:]:
            ax.set_yticklabels([])
        time_ax = fig.add_subplot(grid[2 * i + 1, :])
        _time_panel(time_ax, part, conditions, rows, cols, methods)
        time_ax.set_title(
            f"{(model + ': ') if model else ''}time per instance, log scale (ours: {hardware}; "
            f"paper: {PAPER_HARDWARE}); proofs beside the paper, refutations apart",
            fontsize="small",
        )
        legend.update(zip(*reversed(time_ax.get_legend_handles_labels())))
    fig.legend(
        list(legend.values()),
        list(legend),
        loc="outside lower center",
        ncol=max(2, min(4, int(width // 3.5))),
        fontsize=7,
    )
    if image is not None:
        fig.colorbar(image, ax=fig.axes[:n_panels], shrink=0.8, label="verified rate")
    seeds = cells.loc[cells["method"] != "pb", "seeds_inside"].dropna()
    smoke = (
        f"\nsmoke test: as few as {int(seeds.min())} seeds inside Ξ in a cell (fewer than "
        f"{MIN_SEEDS}): the intervals are wide, nothing here is a finding"
        if len(seeds) and seeds.min() < MIN_SEEDS
        else ""
    )
    fig.suptitle(
        f"{title}\nverified rate (holds among seeds inside Ξ) with its 95 % interval and time, "
        f"ours beside the paper's (its interval: 200 seeds){smoke}"
    )
    return fig


def _keys(cells: pd.DataFrame, columns: list[str]) -> list[tuple]:
    """The distinct values of ``columns`` in ``cells``, sorted."""
    if not columns:
        return [()]
    return sorted(set(cells[columns].itertuples(index=False, name=None)))


def _lookup(part: pd.DataFrame, conditions, rows, cols, column: str) -> np.ndarray:
    """``part[column]`` on the grid ``(len(rows), len(cols))``, NaN where no cell."""
    grid = np.full((len(rows), len(cols)), np.nan)
    index_r = {k: n for n, k in enumerate(rows)}
    index_c = {k: n for n, k in enumerate(cols)}
    keys_r = part[conditions].itertuples(index=False, name=None) if conditions else [()] * len(part)
    keys_c = part[list(GRID_COLUMNS)].itertuples(index=False, name=None)
    for kr, kc, value in zip(keys_r, keys_c, part[column]):
        grid[index_r[tuple(kr)], index_c[tuple(kc)]] = value
    return grid


def _rate_grid(ax, part, conditions, rows, cols, norm, ours: bool):
    """One rate grid: ours (annotated with the paper's rate and the difference) or the
    paper's; NaN cells hatched. Returns the image (for the colour bar)."""
    paper = _lookup(part, conditions, rows, cols, "paper_rate")
    values = _lookup(part, conditions, rows, cols, "rate") if ours else paper
    bounds = {
        c: _lookup(part, conditions, rows, cols, c)
        for c in ("rate_lo", "rate_hi", "paper_rate_lo", "paper_rate_hi")
    }
    image = ax.imshow(
        np.ma.masked_invalid(values), cmap="viridis", norm=norm, aspect="auto", zorder=1
    )
    ax.add_patch(
        Rectangle(
            (-0.5, -0.5), len(cols), len(rows), hatch="///", fill=False, ec="0.75", lw=0, zorder=0
        )
    )
    seeds = _lookup(part, conditions, rows, cols, "seeds_inside") if ours else None
    present = _lookup(part, conditions, rows, cols, "instances") if ours else None
    for r in range(len(rows)):
        for c in range(len(cols)):
            ours_ci = (bounds["rate_lo"][r, c], bounds["rate_hi"][r, c])
            paper_ci = (bounds["paper_rate_lo"][r, c], bounds["paper_rate_hi"][r, c])
            text, value = _cell_text(
                values[r, c], paper[r, c], ours, seeds, present, r, c, ours_ci, paper_ci
            )
            light = np.isfinite(value) and value > 0.55
            ax.text(
                c, r, text, ha="center", va="center", fontsize=6, zorder=2,
                color="k" if light or not np.isfinite(value) else "w",
            )  # fmt: skip
    ax.set_xticks(range(len(cols)), [f"κ={k:g}\nα={a:g}" for k, a in cols], fontsize=7)
    ax.set_yticks(range(len(rows)), [_row_label(conditions, k) for k in rows], fontsize=7)
    ax.set_xlim(-0.5, len(cols) - 0.5)
    ax.set_ylim(len(rows) - 0.5, -0.5)
    return image


def _cell_text(value, paper, ours, seeds, present, r, c, ours_ci, paper_ci) -> tuple[str, float]:
    if not ours:
        text = f"{paper:.0%}\n{_interval(*paper_ci)}" if np.isfinite(paper) else "no cell"
        return text, paper
    if not np.isfinite(present[r, c]):
        return "no data", value
    if not np.isfinite(value):
        return "no seed\nin Ξ", value
    paper_text = f"paper {paper:.0%} {_interval(*paper_ci)}" if np.isfinite(paper) else "paper –"
    delta = f"Δ {100 * (value - paper):+.0f} pp" if np.isfinite(paper) else ""
    lines = (f"ours {value:.0%} {_interval(*ours_ci)}", paper_text, delta)
    return "\n".join(t for t in lines if t), value


def _interval(low: float, high: float) -> str:
    """A 95 % interval in percent, ``(44–56)``."""
    return f"({100 * low:.0f}–{100 * high:.0f})" if np.isfinite(low) else ""


def _row_label(conditions, key) -> str:
    names = {"kind": "", "level": "", "m": "m=", "overlapping": ""}
    parts = []
    for c, v in zip(conditions, key):
        if c == "overlapping":
            parts.append("overlapping" if bool(v) else "apart")
        elif c == "level":
            parts.append(f"{v:g}")
        else:
            parts.append(f"{names[c]}{v:g}" if not isinstance(v, str) else str(v))
    return " ".join(parts) or "all"


def _counts(part: pd.DataFrame) -> str:
    """``holds / violated / unknown`` of a method's cells (``?`` where not stored), the
    allocation method's ``not_certifiable`` where there are any; for the pose-bound
    method, how many holds are exact and how many rest on the linearised bound."""
    text = "holds/violated/unknown " + "/".join(
        "?" if part[c].isna().all() else str(int(part[c].sum()))
        for c in ("holds", "violated", "unknown")
    )
    if part["not_certifiable"].fillna(0).gt(0).any():
        text += f"\nnot certifiable (pixel grid > ε): {int(part['not_certifiable'].sum())}"
    if part["exact_holds"].notna().any() and part["holds"].notna().any():
        exact = int(part["exact_holds"].sum())
        text += f"\n(holds: {exact} exact, {int(part['holds'].sum()) - exact} linearised bound)"
    return text


def _time_panel(ax, part, conditions, rows, cols, methods):
    """Time per instance cell by cell (log scale): proofs filled, refutations hollow, the
    paper's mean ± std in black; a table without the split shows the mean over all."""
    keys = [(r, c) for r in rows for c in cols]
    present = [
        (r, c) for r, c in keys if not part[_mask(part, conditions, r, c)]["instances"].isna().all()
    ]
    x = np.arange(len(present))
    width = 0.8 / (len(methods) + 1)
    drawn = []
    for j, method in enumerate(methods):
        mine = part[part["method"] == method]
        color = f"C{j}"
        shift = -0.4 + width * (j + 0.5)
        proof = np.array([_value(mine, conditions, r, c, "time_proof") for r, c in present])
        refute = np.array([_value(mine, conditions, r, c, "time_refute") for r, c in present])
        undecided = np.array([_value(mine, conditions, r, c, "time_unknown") for r, c in present])
        split = mine["time_proof"].notna().any() or mine["time_refute"].notna().any()
        if split:
            ax.scatter(x + shift, proof, marker="o", color=color, s=22, zorder=3,
                       label=f"{method}: proofs (holds)")  # fmt: skip
            ax.scatter(x + shift, refute, marker="v", facecolors="none", edgecolors=color,
                       s=26, zorder=3, label=f"{method}: refutations (violated)")  # fmt: skip
            if np.isfinite(undecided).any():
                ax.scatter(x + shift, undecided, marker="x", color=color, s=22, zorder=3,
                           lw=1, label=f"{method}: unknown (budget spent)")  # fmt: skip
            drawn += [proof, refute, undecided]
            drawn += _quartiles(ax, mine, conditions, present, x + shift + width / 3, color, method)
        else:  # a table from before the split: all instances together
            every = np.array([_value(mine, conditions, r, c, "time_all") for r, c in present])
            ax.scatter(x + shift, every, marker="s", color=color, s=18, zorder=3,
                       label=f"{method}: all instances (table without the split)")  # fmt: skip
            drawn.append(every)
    mean = np.array([_value(part, conditions, r, c, "paper_time_mean") for r, c in present])
    std = np.array([_value(part, conditions, r, c, "paper_time_std") for r, c in present])
    drawn.append(mean + np.nan_to_num(std))
    finite = np.concatenate([d[np.isfinite(d) & (d > 0)] for d in drawn] + [np.array([1.0])])
    low = 10 ** np.floor(np.log10(finite.min() / 2))
    high = 10 ** np.ceil(np.log10(finite.max() * 2))
    shift = -0.4 + width * (len(methods) + 0.5)
    ok = np.isfinite(mean)
    lower = np.clip(mean - np.nan_to_num(std), low, None)
    ax.errorbar(
        x[ok] + shift, mean[ok], yerr=[mean[ok] - lower[ok], np.nan_to_num(std)[ok]],
        fmt="D", color="k", ms=4, capsize=2, lw=1, zorder=3,
        label=f"paper ({PAPER_HARDWARE}): mean ± std, all instances",
    )  # fmt: skip
    ax.set_yscale("log")
    ax.set_ylim(low, high)
    ax.set_ylabel("seconds per instance")
    labels = [
        f"{_row_label(conditions, r)} κ={c[0]:g} α={c[1]:g}" if conditions else
        f"κ={c[0]:g} α={c[1]:g}"
        for r, c in present
    ]  # fmt: skip
    ax.set_xticks(x, labels, rotation=45, ha="right", fontsize=6.5)
    ax.set_xlim(-0.6, max(len(present), 1) - 0.4)
    ax.grid(axis="y", which="major", alpha=0.3)


def _quartiles(ax, mine, conditions, present, x, color, method) -> list[np.ndarray]:
    """A method's median time over all instances of each cell (a bar) with its quartiles
    (a line), beside its means; nothing for a table from before the quartiles."""
    q1, median, q3 = (
        np.array([_value(mine, conditions, r, c, column) for r, c in present])
        for column in ("time_q1", "time_median", "time_q3")
    )
    ok = np.isfinite(median)
    if not ok.any():
        return []
    ax.vlines(x[ok], q1[ok], q3[ok], color=color, lw=1, alpha=0.7, zorder=2)
    ax.scatter(x[ok], median[ok], marker="_", color=color, s=40, lw=1.5, zorder=3,
               label=f"{method}: median and quartiles, all instances")  # fmt: skip
    return [q1, q3]


def _mask(part, conditions, row, col) -> np.ndarray:
    mask = np.ones(len(part), bool)
    for c, v in zip((*conditions, *GRID_COLUMNS), (*row, *col)):
        mask &= (part[c] == v).to_numpy()
    return mask


def _value(part, conditions, row, col, column) -> float:
    values = part.loc[_mask(part, conditions, row, col), column].dropna()
    return float(values.iloc[0]) if len(values) else np.nan


def save_comparison(
    table_csv, png, title: str | None = None, hardware: str | None = None, dpi: int = 130
):
    """Draw :func:`plot_comparison` of the table ``table_csv`` (a ``tables/*.csv`` of a
    results folder) to ``png`` at ``dpi``; ``title`` defaults to the file's stem. Returns
    the path."""
    from pathlib import Path

    from kpstudy.io import save_figure

    table_csv = Path(table_csv)
    if not table_csv.is_file():
        raise ValueError(f"table_csv: expected a table's CSV file, got {str(table_csv)!r}")
    fig = plot_comparison(pd.read_csv(table_csv), title or table_csv.stem, hardware)
    return save_figure(fig, png, dpi=dpi)


#: Per method: the record field that says what ended its search (``'time'``: the cap),
#: the table column that counts those instances, and the method's short name.
_CAPS = (("stopped", "capped", "alloc"), ("pb_stopped", "pb_capped", "pb"))
#: At most this many cells are named per group of :func:`time_caps`.
_NAMED = 10


def capped_searches(frame: pd.DataFrame) -> dict[str, int]:
    """Where a time cap, not the node budget, ended a search in a verification table or
    its records.

    Parameters
    ----------
    frame : DataFrame
        A :mod:`kpstudy.study.tables` table (``capped``, ``pb_capped``: counts per cell)
        or its campaign records (``stopped``, ``pb_stopped`` = ``'time'``), as returned or
        read back from CSV; a frame without ``kappa`` and ``alpha`` is neither.

    Returns
    -------
    dict
        ``{'<cell or instance> [<method>]': instances}`` (the cell's words:
        :func:`kpstudy.study.tables.instance_label`; the method ``alloc`` or ``pb``), for
        every row and method whose cap fired, in the frame's order; ``{}`` without any.

    Examples
    --------
    >>> records = pd.DataFrame({"model": ["cnn", "cnn"], "image_id": [0, 1],
    ...                         "kappa": 1.0, "alpha": 1.0, "stopped": ["nodes", "time"]})
    >>> capped_searches(records)
    {'cnn image 1 α=1 κ=1 [alloc]': 1}
    """
    found: dict[str, int] = {}
    for method, counts in _cap_counts(frame):
        for i in np.flatnonzero(counts > 0):
            key = f"{instance_label(frame.iloc[i])} [{method}]"
            found[key] = found.get(key, 0) + int(counts[i])
    return found


def _cap_counts(frame: pd.DataFrame) -> list[tuple[str, np.ndarray]]:
    """Per method the frame records, the searches its cap ended in each row (records:
    0 or 1; tables: the ``capped`` count); ``[]`` for a frame that is not a verification
    table or its records."""
    if not {"kappa", "alpha"} <= set(frame.columns):
        return []
    out = []
    for stopped, capped, method in _CAPS:
        if stopped in frame:
            counts = (frame[stopped].astype(str) == "time").to_numpy(np.int64)
        elif capped in frame:
            counts = np.nan_to_num(_numeric(frame, capped)).astype(np.int64)
        else:
            continue
        out.append((method, counts))
    return out


def time_caps(a: pd.DataFrame, b: pd.DataFrame, differing=None) -> str:
    """What two runs' versions of a table or its records say about fired time caps, to
    append to what differs between them (:func:`kpstudy.study.reproduction.compare_results`).

    Parameters
    ----------
    a, b : DataFrame
        The same ``tables/*.csv`` of two results folders, as read back.
    differing : array of bool, optional
        Per row, whether the runs' rows differ (where the frames have the same rows): then
        how many of the differing rows had no cap fire in either run is added.

    Returns
    -------
    str
        ``''`` when no cap fired in either run (or the frames are neither a verification
        table nor records, :func:`capped_searches`); else ``'; time cap fired …'`` naming
        the cells and methods where it fired in a only, in b only and in both runs (a
        count ``×n`` where a cell holds more than one), whose verdicts depend on the
        machine's speed.

    Examples
    --------
    >>> a = pd.DataFrame({"image_id": [0, 1], "kappa": 1.0, "alpha": 1.0,
    ...                   "status": ["holds", "unknown"], "stopped": [None, "time"]})
    >>> b = a.assign(status=["holds", "holds"], stopped=[None, None])
    >>> print(time_caps(a, b, np.array([False, True])))  # doctest: +NORMALIZE_WHITESPACE
    ; time cap fired (not the node budget: the verdict depends on the machine's speed) in
    a only: image 1 α=1 κ=1 [alloc]; rows that differ with no cap fired in either run: 0 of 1
    >>> time_caps(b, b)
    ''
    """
    in_a, in_b = capped_searches(a), capped_searches(b)
    if not in_a and not in_b:
        return ""
    groups = (
        ("a only", [k for k in in_a if k not in in_b]),
        ("b only", [k for k in in_b if k not in in_a]),
        ("both runs", [k for k in in_a if k in in_b]),
    )
    parts = [f"in {where}: {_cap_names(keys, in_a, in_b)}" for where, keys in groups if keys]
    text = (
        "; time cap fired (not the node budget: the verdict depends on the machine's speed) "
        + "; ".join(parts)
    )
    if differing is not None and len(differing) == len(a) == len(b):
        differing = np.asarray(differing, dtype=bool)
        fired = np.zeros(len(a), dtype=bool)
        for _, counts in [*_cap_counts(a), *_cap_counts(b)]:
            fired |= counts > 0
        text += (
            f"; rows that differ with no cap fired in either run: "
            f"{int((differing & ~fired).sum())} of {int(differing.sum())}"
        )
    return text


def _cap_names(keys: list[str], in_a: dict, in_b: dict) -> str:
    """``keys`` joined, each with its count where above 1 (``×2``; ``×2 in a, ×1 in b``
    where the runs' counts differ), at most :data:`_NAMED` and then how many more."""
    names = []
    for key in keys[:_NAMED]:
        n_a, n_b = in_a.get(key), in_b.get(key)
        if n_a and n_b and n_a != n_b:
            names.append(f"{key} ×{n_a} in a, ×{n_b} in b")
        else:
            n = n_a or n_b
            names.append(f"{key} ×{n}" if n > 1 else key)
    more = f", and {len(keys) - _NAMED} more" if len(keys) > _NAMED else ""
    return ", ".join(names) + more
