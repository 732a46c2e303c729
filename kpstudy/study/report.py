"""``results/<profile>/REPORT.md``: every table and figure of a run, the paper beside ours,
and a short reading of the trends computed from the tables (never written by hand).

:func:`write_report` reads what the notebooks wrote under ``tables/`` and ``figures/``;
a missing table or figure is listed as missing rather than skipped silently. The
verification tables (T-local, T-global, T-resnet: :data:`COMPARED`) are shown as their
figure (:func:`kpstudy.study.comparison.plot_comparison`), a compact table of the numbers a
reader compares (:func:`kpstudy.study.comparison.compact_table`), a link to the full CSV and
the full table folded; their readings say where our 95 % intervals and the paper's
overlap (:func:`interval_readings`), whether a cell's seeds make it a smoke test, what the
pixel grid alone rules out (``not_certifiable``), how many searches a time cap rather than
a node budget ended (verdicts that depend on the machine's speed), and test each trend the
paper states at 95 % (:mod:`kpstudy.study.trends`) on our numbers and on the paper's; the
instances of their records (``tables/<name>_records.csv``) that ended ``'error'`` are
listed (:func:`error_instances`, :func:`error_markdown`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from kpstudy.io import write_text_atomic
from kpstudy.study.comparison import CONDITIONS, GRID_COLUMNS, compact_table, method_cells
from kpstudy.study.tables import instance_label, reading_comparison
from kpstudy.study.trends import LEVEL, MIN_SEEDS, PAPER_SEEDS, trend_table

__all__ = [
    "COMPARED",
    "LISTED_ERRORS",
    "SECTIONS",
    "campaign_summary",
    "compact_markdown",
    "error_instances",
    "error_markdown",
    "interval_readings",
    "not_certifiable_reading",
    "smoke_test_reading",
    "t_prob_readings",
    "time_cap_reading",
    "trend_markdown",
    "trend_readings",
    "run_cost",
    "cost_markdown",
    "budget_markdown",
    "write_report",
]

#: (title, notebook, tables, figures, what it reproduces)
SECTIONS = (
    (
        "F-data: dataset and perturbations",
        "01_data",
        ["f_data"],
        ["renders", "occluders", "perturbations"],
        "paper §8.1, Figs. 5–6",
    ),
    ("Trained backbones", "02_training", ["training"], ["training"], "paper §8.1"),
    (
        "F-sym: heatmap symmetry",
        "03_symmetry",
        ["f_sym"],
        ["f_sym"],
        "paper Fig. 8 (table: median and 90th percentile over maps of each indicator's "
        "magnitude, |skewness|, |mean − median|, |mean − mode|, and of the IQR)",
    ),
    (
        "F-alloc and F-kps: allocated tolerances",
        "04_allocation",
        [],
        ["f_alloc", "f_kps"],
        "paper Figs. 9–10 (table: tables/f_alloc.csv)",
    ),
    (
        "T-prob: probabilistic soundness and completeness",
        "05_probabilistic",
        ["t_prob"],
        [],
        "paper Table 2",
    ),
    (
        "T-local: object occlusions, CNN",
        "06_local",
        ["t_local"],
        ["t_local", "t_local_pose_bound"],
        "paper Tables 3–4",
    ),
    (
        "T-global: brightness and contrast, CNN",
        "07_global",
        ["t_global"],
        ["t_global", "t_global_pose_bound"],
        "paper Tables 5–6",
    ),
    (
        "T-resnet: block occlusions, ResNet-18",
        "08_resnet",
        ["t_resnet"],
        ["t_resnet", "t_resnet_pose_bound"],
        "paper §8.4",
    ),
)


#: The tables shown as figure + compact table (their figure has the table's name).
COMPARED = ("t_local", "t_global", "t_resnet")
#: At most this many error instances are listed per table (then a count of the rest).
LISTED_ERRORS = 20
#: At most this many capped cells are named per model and reading.
_NAMED_CELLS = 10


def write_report(out, profile: dict | None = None) -> Path:
    """Assemble ``out/REPORT.md`` from ``out/tables`` and ``out/figures``; ``profile``:
    the run's settings, listed first. Returns the path of ``REPORT.md``."""
    out = Path(out)
    tables, figures = out / "tables", out / "figures"
    lines = [
        f"# kpstudy: {out.name} profile",
        "",
        "Written by `python -m kpstudy reproduce`; every number below comes from the tables "
        "beside this file (`tables/*.csv`), produced by the notebooks in `notebooks/`. Paper "
        "columns are the numbers of the paper (ModelVerification.jl on an RTX A4000). For "
        "T-local, T-global and T-resnet, a figure shows every method beside the paper (the "
        "allocation method `alloc` under each tolerance reading, the pose-bound method "
        "`pb`), then a compact table and the full one (folded, and as CSV).",
        "",
    ]
    if profile:
        lines += ["| setting | value |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in profile.items()]
        lines.append("")
    lines += cost_markdown(run_cost(out))
    errors = error_instances(out)
    readers = {
        "t_prob": t_prob_readings,
        "t_local": _campaign,
        "t_global": _campaign,
        "t_resnet": _campaign,
    }
    for title, notebook, names, pictures, source in SECTIONS:
        lines += [f"## {title}", "", f"Notebook `notebooks/{notebook}.ipynb`; {source}.", ""]
        for name in names:
            md = tables / f"{name}.md"
            if not md.is_file():
                lines += [f"*Table `{name}` is missing (its notebook has not run).*", ""]
                lines += error_markdown(name, errors.get(name))
                continue
            table = pd.read_csv(tables / f"{name}.csv")
            if name in COMPARED:
                lines += _compared(name, table, md, figures)
            else:
                lines += [md.read_text().rstrip(), ""]
            if name in readers:
                text = readers[name](table)
                trends = trend_markdown(trend_readings(name, table))
                lines += ["**Reading.**", "", *[f"- {t}" for t in text], ""]
                lines += [trends, ""] if trends else []
            if name in COMPARED:
                lines += budget_markdown(tables / f"{name}_records.csv")
            lines += error_markdown(name, errors.get(name))
        for picture in pictures:
            if picture in COMPARED and picture in names:
                continue  # drawn above, with its compact table
            png = figures / f"{picture}.png"
            lines += (
                [f"![{picture}](figures/{picture}.png)", ""]
                if png.is_file()
                else [f"*Figure `{picture}` is missing.*", ""]
            )
    return write_text_atomic(out / "REPORT.md", "\n".join(lines))


def run_cost(out) -> pd.DataFrame:
    """What each verification table of the run at ``out`` cost, from its records
    (``tables/<name>_records.csv`` with ``image_id`` and ``total_time``), and what the
    paper's seed count would cost at the same seconds per instance.

    Returns
    -------
    DataFrame
        One row per table of :data:`COMPARED` that has records: ``table``, ``seeds`` (seed
        images), ``instances`` (records: every model, reading and cell), ``hours``
        (summed ``total_time``, one worker's hours; the pose-bound method's search of a
        hull is in its first cell's), ``median_s`` (seconds per instance), ``paper_hours``
        (``hours × PAPER_SEEDS / seeds``), ``peak_gib`` (the largest campaign worker's
        resident memory, GiB, from the records' ``peak_memory_mib``; NaN where not
        recorded): the memory each of the paper profile's workers needs as well, since its
        instances are the same size.
    """
    rows = []
    for name in COMPARED:
        path = Path(out) / "tables" / f"{name}_records.csv"
        if not path.is_file():
            continue
        records = pd.read_csv(
            path, usecols=lambda c: c in ("image_id", "total_time", "peak_memory_mib")
        )
        if records.empty or not {"image_id", "total_time"} <= set(records):
            continue
        seeds = records["image_id"].nunique()
        hours = records["total_time"].sum() / 3600
        rows.append(
            dict(
                table=name,
                seeds=seeds,
                instances=len(records),
                hours=hours,
                median_s=records["total_time"].median(),
                paper_hours=hours * PAPER_SEEDS / seeds,
                peak_gib=records.get("peak_memory_mib", pd.Series(dtype=float)).max() / 1024,
            )
        )
    return pd.DataFrame(
        rows,
        columns=["table", "seeds", "instances", "hours", "median_s", "paper_hours", "peak_gib"],
    )


def budget_markdown(records_csv) -> list[str]:
    """The report's lines on how much each search had decided by each node count
    (:func:`kpstudy.study.tables.decided_by_nodes` of a table's records), for choosing
    node budgets; none without the records or node counts."""
    from kpstudy.study.tables import decided_by_nodes

    path = Path(records_csv)
    if not path.is_file():
        return []
    shares = decided_by_nodes(pd.read_csv(path))
    if shares.empty:
        return []
    marks = [c for c in shares.columns if c.startswith("≤ ")]
    lines = [
        "**Decided by node count.** The share of instances each search had decided (holds "
        "or violated) within N nodes, as this run's searches went: what a smaller node "
        "budget decides at least, and what the run's own budget gained over it.",
        "",
        "| model | reading | method | instances | " + " | ".join(marks) + " | at its budget |",
        "|---" * (len(marks) + 5) + "|",
    ]
    for row in shares.to_dict("records"):
        cells = [row["model"], row["tolerance_units"], row["method"], str(row["instances"])]
        cells += [_share(row[mark]) for mark in marks] + [_share(row["decided"])]
        lines.append("| " + " | ".join(cells) + " |")
    return [*lines, ""]


def _share(value) -> str:
    return "–" if pd.isna(value) else f"{value:.0%}"


def cost_markdown(cost: pd.DataFrame) -> list[str]:
    """The report's opening lines on :func:`run_cost`: this run's cost per table and the
    paper profile's at the same seconds per instance (none when no table has records)."""
    if cost.empty:
        return []
    lines = [
        "**Cost.** Per verification table, this run's seconds summed over its instances "
        "(one worker's time; `workers` processes share the cores) and the paper profile's "
        f"at the same seconds per instance on {PAPER_SEEDS} seeds: a lower bound, since "
        "the paper profile's budgets are seconds (600 s an instance), not nodes. It runs "
        "on a Dask cluster with `python -m kpstudy reproduce --profile paper --scheduler "
        "tcp://HOST:8786` (`dask scheduler` on one machine, `dask worker tcp://HOST:8786` "
        "on each of the others). Memory: the largest campaign worker's resident set, which "
        "each of the paper profile's workers needs too (its instances are the same size).",
        "",
        "| table | seeds | instances | hours | median s / instance | paper profile, hours "
        "| largest worker, GiB |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in cost.itertuples(index=False):
        memory = "–" if pd.isna(r.peak_gib) else f"{r.peak_gib:.1f}"
        lines.append(
            f"| {r.table} | {r.seeds} | {r.instances} | {r.hours:.2f} | {_sec(r.median_s)} | "
            f"{r.paper_hours:.1f} | {memory} |"
        )
    return [*lines, ""]


def _compared(name: str, table: pd.DataFrame, md: Path, figures: Path) -> list[str]:
    """A verification table's figure, compact table, links and folded full table."""
    png = figures / f"{name}.png"
    lines = (
        [f"![{name}](figures/{name}.png)", ""]
        if png.is_file()
        else [f"*Figure `{name}` is missing.*", ""]
    )
    lines += [
        f"Per model and method: counts over the table, verified rate ours (holds among the "
        f"seeds inside Ξ over the cells where the paper has one) and the paper's (mean over "
        f"those cells), each with its {LEVEL:.0%} Wilson interval (the paper's over 200 "
        f"seeds per cell; the seeds recur from cell to cell, so pooled intervals are if "
        f"anything too narrow), seconds per instance over our proofs and our refutations "
        f"apart, the range of the cells' median times over all instances, and the paper's "
        f"mean. Full table: "
        f"[tables/{name}.csv](tables/{name}.csv) ({table.shape[1]} columns); records: "
        f"[tables/{name}_records.csv](tables/{name}_records.csv).",
        "",
        compact_markdown(compact_table(table)),
        "",
        f"<details><summary>Full table <code>{name}</code> ({len(table)} rows × "
        f"{table.shape[1]} columns)</summary>",
        "",
        md.read_text().rstrip(),
        "",
        "</details>",
        "",
    ]
    return lines


def compact_markdown(compact: pd.DataFrame) -> str:
    """:func:`kpstudy.study.comparison.compact_table` as a GitHub Markdown table: rates in %
    with their 95 % interval, differences in percentage points, seconds to 3 significant
    digits, ``–`` where there is no number (``?``: a count the table does not have)."""
    head = (
        "| model | method | instances | holds / violated / unknown / not certifiable | cells "
        "| verified rate (95 % CI) | paper (95 % CI) | Δ | proofs (s) | refutations (s) "
        "| cell medians (s) | paper (s) |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in compact.itertuples(index=False):
        counts = " / ".join(_count(v) for v in (r.holds, r.violated, r.unknown))
        counts += " / " + ("–" if r.method == "pb" else _count(r.not_certifiable))
        medians = (
            "–" if pd.isna(r.median_low_s) else f"{_sec(r.median_low_s)}–{_sec(r.median_high_s)}"
        )
        lines.append(
            f"| {r.model or '–'} | {r.method} | {int(r.instances)} | {counts} | {r.cells} | "
            f"{_pct(r.rate, r.rate_lo, r.rate_hi)} | "
            f"{_pct(r.paper_rate, r.paper_rate_lo, r.paper_rate_hi)} | {_pp(r.delta)} | "
            f"{_sec(r.proof_s)} | {_sec(r.refutation_s)} | {medians} | {_sec(r.paper_s)} |"
        )
    return "\n".join(lines)


def _count(value) -> str:
    return "?" if value is None or pd.isna(value) else str(int(value))


def _pct(value, low=None, high=None) -> str:
    """A rate in %, with its interval ``(low–high)`` in % where given."""
    if pd.isna(value):
        return "–"
    if low is None or pd.isna(low):
        return f"{value:.0%}"
    return f"{value:.0%} ({100 * low:.0f}–{100 * high:.0f})"


def _pp(value) -> str:
    return "–" if pd.isna(value) else f"{100 * value:+.0f} pp"


def _sec(value) -> str:
    return "–" if pd.isna(value) else f"{value:.3g}"


def trend_readings(name: str, table: pd.DataFrame) -> pd.DataFrame:
    """The trends the paper states (:data:`kpstudy.study.trends.STATEMENTS`) that table
    ``name`` can test (:func:`kpstudy.study.trends.trend_table`): for T-prob per tolerance
    reading; for a verification table per model and method
    (:func:`kpstudy.study.comparison.method_cells`)."""
    if name == "t_prob":
        series = ["tolerance_units"] if "tolerance_units" in table else []
        reading = (lambda v: f"ours, '{v[0]}' reading") if series else None
        return trend_table(table, ["kappa", "alpha"], series, label=reading)
    cells = method_cells(table)
    keys = [*(c for c in CONDITIONS if c in cells), *GRID_COLUMNS]
    series = ["model", "method"] if cells["model"].astype(bool).any() else ["method"]
    return trend_table(cells, keys, series)


def trend_markdown(trends: pd.DataFrame) -> str:
    """:func:`trend_readings` as a Markdown table (a statement per row), with a line
    saying how to read it; ``''`` without any statement."""
    if trends.empty:
        return ""
    head = "| the paper states | " + " | ".join(trends.columns) + " |"
    rule = "|---|" + "---|" * len(trends.columns)
    rows = [
        f"| *{text}* | " + " | ".join(str(v) for v in row) + " |"
        for text, row in zip(trends.index, trends.itertuples(index=False))
    ]
    return "\n".join(
        [
            f"The trends the paper states, tested at {LEVEL:.0%} on the numbers: the cells "
            "that differ only in that axis are paired (its smallest value against its "
            "largest) and the two ends compared, pooled over the pairs: *shown* when they "
            "differ significantly in the paper's direction, *contradicted* when they differ "
            "significantly against it, *not shown* otherwise (a rate: Fisher's exact test "
            "on the holds among the seeds inside Ξ, the paper's over its 200 seeds per "
            "cell; soundness and completeness: on the Monte Carlo samples, the paper's "
            "3000 × 5000, which cluster by image, so the test is if anything too "
            "confident there; a time per instance: Welch's t-test on the mean, from each "
            "cell's mean, standard deviation and count, the paper's over 200 instances). "
            "Then how many pairs move as the paper states, against it, or not at all, and "
            f"the mean change. A *smoke test* has fewer than {MIN_SEEDS} seeds (instances, "
            "for a time) in a cell: its verdict is computed, never a finding.",
            "",
            head,
            rule,
            *rows,
        ]
    )


def _per_group(read, compare: tuple[str, str, str] | None = None):
    """``read(table)``, once per ``model`` and tolerance reading (its lines prefixed by
    them) when the table has them; with ``compare`` (ours, paper, name), first each
    model's sentence of :func:`kpstudy.study.tables.reading_comparison`."""

    def readings(table):
        keys = [c for c in ("model", "tolerance_units") if c in table]
        lines = []
        if compare is not None:
            models = table.groupby("model", sort=True) if "model" in table else [("", table)]
            for model, part in models:
                sentence = reading_comparison(part, *compare)
                if sentence:
                    lines.append((f"`{model}`: " if model else "") + sentence)
        for key, part in table.groupby(keys, sort=True) if keys else [((), table)]:
            key = key if isinstance(key, tuple) else (key,)
            prefix = "".join(
                f"`{v}`: " if k == "model" else f"'{v}' reading: " for k, v in zip(keys, key)
            )
            lines += [prefix + line for line in read(part)]
        return lines

    return readings


def t_prob_readings(table: pd.DataFrame) -> list[str]:
    """Soundness and completeness against the paper's, per tolerance reading, after the
    sentence comparing the readings with the paper (how they move with κ and α:
    :func:`trend_readings`)."""
    return _per_group(_t_prob, ("soundness", "paper_soundness", "Soundness"))(table)


def _t_prob(table: pd.DataFrame) -> list[str]:
    s = table.pivot(index="kappa", columns="alpha", values="soundness")
    c = table.pivot(index="kappa", columns="alpha", values="completeness")
    paper = table.pivot(index="kappa", columns="alpha", values="paper_soundness")
    return [
        f"Soundness from {s.to_numpy().min():.4g} to {s.to_numpy().max():.4g} over the cells "
        f"(paper {table.paper_soundness.min():.4g}–{table.paper_soundness.max():.4g}).",
        f"Completeness at most {c.to_numpy().max():.3g} (paper at most "
        f"{table.paper_completeness.max():.3g}): the share of poses in Ξ whose keypoints stay "
        "in the allocated boxes.",
        f"At κ = {s.index[0]:g}, soundness from α = {s.columns[0]:g} to {s.columns[-1]:g}: "
        f"{s.iloc[0, 0]:.4g} → {s.iloc[0, -1]:.4g} (paper {paper.iloc[0, 0]:.4g} → "
        f"{paper.iloc[0, -1]:.4g}).",
    ] + (
        [
            f"The same integer boxes read as heatmap pixels (the cells the verifier proves) "
            f"keep {table.soundness_true_units.min():.4g}–{table.soundness_true_units.max():.4g} "
            "of their vertices' poses in Ξ."
        ]
        if "soundness_true_units" in table and (table.get("tolerance_units") == "paper").all()
        else []
    )


def campaign_summary(table: pd.DataFrame) -> list[str]:
    """The counts of a verification table's records (of one model and reading), what the
    'paper' reading lets through, the allocation's one-pixel cells and the pose-bound
    method's verdicts and rules."""
    lines = []
    total = int(table.instances.sum())
    holds, inside = int(table.holds.sum()), int(table.seeds_inside.sum())
    at_seed = int(table.violated_at_seed.sum())
    lines.append(
        f"{total} instances: {holds} holds, {int(table.violated.sum())} violated "
        f"({at_seed} of them at the seed image itself, λ = 0), {int(table.unknown.sum())} "
        f"unknown"
        + (
            f", {int(table.not_certifiable.sum())} not certifiable at the heatmap's resolution"
            if "not_certifiable" in table
            else ""
        )
        + (
            f", {int(table.errors.sum())} that could not be run (errors, e.g. a keypoint "
            "outside the heatmap)"
            if "errors" in table
            else ""
        )
        + f"; {inside} had the seed's target-model pose inside Ξ."
    )
    if "argmax_outside" in table and table.argmax_outside.notna().any():
        lines.append(
            f"Of the sampled hull images of its holds, {table.argmax_outside.mean():.1%} (mean "
            "over cells) have an argmax → PnP pose outside Ξ: what this reading lets through."
        )
    if "dv_zero" in table:
        lines.append(
            f"The allocation gave {table.dv_zero.mean():.0%} of the keypoint coordinates "
            f"δv = 0 (a one-pixel cell) and a mean δv of {table.dv_mean.mean():.2f} heatmap "
            "px: a one-pixel cell holds only if the network's peak is on the rounded "
            "ground-truth pixel, so violations at the seed image itself measure how often "
            "the allocation is tighter than the network's own accuracy."
        )
    if "pb_holds" in table and table.pb_holds.notna().any():
        rate = lambda rate, inside: (  # noqa: E731
            "n/a" if not inside.sum() else f"{(rate * inside).sum() / inside.sum():.1%}"
        )
        pb_inside = table.get("pb_seeds_inside", table.seeds_inside)
        lines.append(
            f"Pose-bound method (reachable keypoint regions → pose decision) on the same "
            f"instances: {int(table.pb_holds.sum())} holds; verified rate "
            f"{rate(table.pb_verified_rate, pb_inside)} of the {int(pb_inside.sum())} seeds "
            "whose argmax → PnP pose lies in Ξ, against the allocation's "
            f"{rate(table.verified_rate, table.seeds_inside)} of the "
            f"{int(table.seeds_inside.sum())} where the target model's does. It verifies "
            f"{int(table.pb_only.sum())} instance(s) the allocation method does not, and the "
            f"allocation method {int(table.allocation_only.sum())} it does not. PnP re-solved "
            f"at region corners leaves Ξ for {int(table.pb_nonlinear_outside.sum())} of its "
            "holds (the linearisation's error, shared with the allocation method). Mean time "
            f"{table.pb_time_mean.mean():.3g} s per instance (one region search per hull, "
            "counted in full for each of its α, κ cells)."
        )
    if "pb_by_enumeration" in table and table.pb_by_enumeration.notna().any():
        lines.append(
            f"Decided by a witness image outside Ξ: {int(table.pb_by_witness.sum())}; by PnP on "
            f"every combination of region pixels (exact for argmax → PnP): "
            f"{int(table.pb_by_enumeration.sum())}, {int(table.pb_enumeration_holds.sum())} of "
            f"them holds; by the linearised bound: {int(table.pb_by_linearised.sum())}."
        )
    lines += not_certifiable_reading(table)
    lines += time_cap_reading(table)
    return lines


#: Per method, the table column that counts the instances whose search its time cap ended.
_CAPPED = (("capped", "allocation method's"), ("pb_capped", "pose-bound method's"))


def time_cap_reading(table: pd.DataFrame) -> list[str]:
    """One sentence on the searches of a verification table (of one model and reading)
    that their time cap ended before their node budget (``capped``, ``pb_capped``: records
    with ``stopped`` / ``pb_stopped`` = ``'time'``): how many per method, in which cells,
    and that those verdicts depend on the machine's speed; that no cap fired when none
    did. ``[]`` for a table from before the columns."""
    methods = [
        (column, name)
        for column, name in _CAPPED
        if column in table and table[column].notna().any()
    ]
    if not methods:
        return []
    counts = [int(pd.to_numeric(table[c], errors="coerce").fillna(0).sum()) for c, _ in methods]
    if not any(counts):
        names = " or the ".join(name for _, name in methods)
        return [
            f"The time cap ended no search of the {names} instances: node budgets (or a "
            "finished search) decided them, so their verdicts do not depend on the machine's "
            "speed."
        ]
    capped = [f"{n} of the {name}" for n, (_, name) in zip(counts, methods)]
    cells = []
    for _, row in table.iterrows():
        per = [
            f"{'allocation' if c == 'capped' else 'pose-bound'} {int(row[c])}"
            for c, _ in methods
            if pd.notna(row[c]) and row[c] > 0
        ]
        if per:
            where = {k: v for k, v in row.items() if k not in ("model", "tolerance_units")}
            cells.append(f"{instance_label(where) or 'the cell'}: {', '.join(per)}")
    named = "; ".join(cells[:_NAMED_CELLS])
    if len(cells) > _NAMED_CELLS:
        named += f"; and {len(cells) - _NAMED_CELLS} more cells"
    return [
        f"**Time caps.** The time cap, not the node budget, ended the search of "
        f"{' and '.join(capped)} instances ({named}): those verdicts depend on the machine's "
        "speed (on a faster or less loaded machine the same budget may decide them, or "
        "decide them otherwise); node budgets decided the others, the same on any machine."
    ]


def error_instances(out) -> dict[str, tuple[int, list[tuple[str, str]]]]:
    """The campaign instances that ended ``'error'``, per verification table
    (:data:`COMPARED`) whose records ``out/tables/<name>_records.csv`` exist: how many
    records the file holds and, for each that ended ``'error'``, its label
    (:func:`kpstudy.study.tables.instance_label`) and its error text. The REPORT
    (:func:`error_markdown`) and ``kpstudy reproduce``
    (:func:`kpstudy.study.reproduction.campaign_errors`) list them from here."""
    found = {}
    for name in COMPARED:
        path = Path(out) / "tables" / f"{name}_records.csv"
        if not path.is_file():
            continue
        records = pd.read_csv(path)
        failed = records[records["status"] == "error"] if "status" in records else records[:0]
        found[name] = (
            len(records),
            [(instance_label(row), _error_text(row.get("error"))) for _, row in failed.iterrows()],
        )
    return found


def _error_text(value) -> str:
    """A record's ``error`` text, or what stands in for one it lacks."""
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "(no error text stored)"
    return str(value)


def error_markdown(name: str, found: tuple[int, list[tuple[str, str]]] | None) -> list[str]:
    """The REPORT's lines listing table ``name``'s instances that ended ``'error'``
    (``found``: its entry of :func:`error_instances`): a sentence with their count, then a
    bullet each (at most :data:`LISTED_ERRORS`, then a count of the rest); ``[]``
    without any."""
    if not found or not found[1]:
        return []
    total, failed = found
    path = f"tables/{name}_records.csv"
    lines = [
        f"**Instances that could not be run.** {len(failed)} of the {total} records of "
        f"[{path}]({path}) ended `error`: they have no verdict, count in the table's "
        "`instances` and `errors` columns only (not in the verified rate), and a campaign "
        "run with `--retry-errors` reruns them.",
        "",
    ]
    for label, text in failed[:LISTED_ERRORS]:
        lines.append(f"- {label}: {_code(text)}")
    if len(failed) > LISTED_ERRORS:
        lines.append(
            f"- and {len(failed) - LISTED_ERRORS} more (every one: the rows of {path} "
            "with status `error`)."
        )
    return lines + [""]


def _code(text: str, limit: int = 300) -> str:
    """``text`` as inline Markdown code on one line, at most ``limit`` characters."""
    text = " ".join(str(text).split())
    if len(text) > limit:
        text = text[: limit - 1] + "…"
    fence = "``" if "`" in text else "`"
    return f"{fence} {text} {fence}" if fence == "``" else f"`{text}`"


def not_certifiable_reading(table: pd.DataFrame) -> list[str]:
    """Per α (and κ where it varies), the fraction of seeds whose pixel grid alone already
    exceeds ε / κ (``not_certifiable``: the paper's method cannot certify them at the
    model's heatmap resolution), among the instances that ran (``instances − errors``), of
    a table of one model; ``[]`` for a table without the column."""
    if "not_certifiable" not in table or not len(table):
        return []
    if "tolerance_units" in table:  # only the sound reading refuses a seed this way
        table = table[table["tolerance_units"] == "heatmap"]
        if not len(table):
            return []
    ran = table["instances"] - (table["errors"] if "errors" in table else 0)
    frame = table.assign(_ran=ran)
    parts = []
    for alpha, at in frame.groupby("alpha", sort=True):
        text = f"α = {alpha:g}: {_fraction(at)}"
        if at["kappa"].nunique() > 1:
            each = [f"κ = {k:g}: {_fraction(c)}" for k, c in at.groupby("kappa", sort=True)]
            text += f" ({', '.join(each)})"
        parts.append(text)
    model = str(table["model"].iloc[0]) if "model" in table else ""
    size = _heatmap_size(model)
    where = (
        f"{size}×{size} heatmaps of `{model}`"
        if size
        else (f"heatmaps of `{model}`" if model else "model's heatmaps")
    )
    return [
        f"The pixel grid alone rules out (status `not_certifiable`: the nearest pixels of "
        f"the exact keypoints already move the pose out of ε / κ, so no cell of the "
        f"{where} certifies the seed; counted in the verified rate's denominator) "
        f"{'; '.join(parts)} of the seeds."
    ]


def _fraction(cells: pd.DataFrame) -> str:
    """``not_certifiable`` ÷ instances that ran, over ``cells``, in %."""
    ran = float(cells["_ran"].sum())
    return "n/a" if not ran else f"{cells['not_certifiable'].sum() / ran:.0%}"


def _heatmap_size(model: str) -> int | None:
    """The heatmap side of a backbone named ``model`` (64 for the CNNs, 256 for
    ResNet-18); None for a name that is not a backbone's."""
    from kpstudy.models.backbones import BACKBONES

    size = getattr(BACKBONES.get(model), "heatmap_size", None)
    return int(size) if size else None


def smoke_test_reading(table: pd.DataFrame) -> list[str]:
    """One sentence when a cell of a verification table has fewer than
    :data:`kpstudy.study.trends.MIN_SEEDS` seeds inside Ξ (the allocation method's; every
    model and reading): the table is a smoke test, not a finding. ``[]`` otherwise."""
    seeds = pd.to_numeric(table["seeds_inside"], errors="coerce").dropna()
    if not len(seeds) or seeds.min() >= MIN_SEEDS:
        return []
    return [
        f"**Smoke test.** A cell has as few as {int(seeds.min())} seeds inside Ξ (at most "
        f"{int(seeds.max())}; a finding needs {MIN_SEEDS} or more per cell): the "
        f"intervals are wide, and no difference from the paper and no verdict on a trend "
        f"below is a finding (each verdict is still computed and says so)."
    ]


def interval_readings(table: pd.DataFrame) -> list[str]:
    """Per model and method of a verification table (:func:`kpstudy.study.comparison.method_cells`),
    where our verified rate's 95 % interval and the paper's overlap and where they do
    not: the cells where ours lies wholly below the paper's, those where it lies wholly
    above (each with both intervals), and how many overlap. ``[]`` without a cell where
    both have a rate."""
    cells = method_cells(table)
    conditions = [c for c in CONDITIONS if c in cells]
    lines = []
    for (model, method), part in cells.groupby(["model", "method"], sort=False):
        both = part.dropna(subset=["rate_lo", "paper_rate_lo"])
        if not len(both):
            continue
        below = both[both["rate_hi"] < both["paper_rate_lo"]]
        above = both[both["rate_lo"] > both["paper_rate_hi"]]
        overlap = len(both) - len(below) - len(above)
        name = f"`{model}` {method}" if model else method
        text = (
            f"{name}: our {LEVEL:.0%} interval of the verified rate overlaps the paper's in "
            f"{overlap} of {len(both)} cells"
        )
        for rows, side in ((below, "below"), (above, "above")):
            if len(rows):
                where = "; ".join(_interval_cell(r, conditions) for _, r in rows.iterrows())
                text += f"; ours lies wholly {side} the paper's in {len(rows)}: {where}"
        lines.append(text + ".")
    return lines


def _interval_cell(row: pd.Series, conditions: list[str]) -> str:
    """A cell's name and both intervals: ``m=2 apart κ=1 α=1: 0–66 % against 48–62 %``."""
    names = []
    for c in conditions:
        value = row[c]
        if c == "overlapping":
            names.append("overlapping" if bool(value) else "apart")
        elif c == "m":
            names.append(f"m={value:g}")
        else:
            names.append(f"{value:g}" if isinstance(value, (int, float, np.number)) else str(value))
    names += [f"κ={row.kappa:g}", f"α={row.alpha:g}"]
    ours = f"{100 * row.rate_lo:.0f}–{100 * row.rate_hi:.0f} %"
    paper = f"{100 * row.paper_rate_lo:.0f}–{100 * row.paper_rate_hi:.0f} %"
    return f"{' '.join(names)}: {ours} against {paper}"


_RATE = ("verified_rate", "paper_rate", "Verified rate (allocation method)")


def _campaign(table: pd.DataFrame) -> list[str]:
    """Whether the table is a smoke test; per model, the readings' comparison with the
    paper; per model and reading, the counts; per model and method, where our intervals
    and the paper's overlap (the paper's trends follow in a table,
    :func:`trend_readings`)."""
    lines = smoke_test_reading(table) + _per_group(campaign_summary, _RATE)(table)
    return lines + interval_readings(table)
