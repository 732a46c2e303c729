"""kpstudy.study.comparison: every method's rate and time beside the paper's, from stored tables."""

import io

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from kpstudy.io import write_table
from kpstudy.study import comparison, tables
from kpstudy.study.reproduction import compare_results
from tests.helpers.records import local_records, wilson


@pytest.fixture(scope="module")
def table():
    return tables.t_local(local_records())


def test_tables_split_times_by_status(table):
    row = table[(table.tolerance_units == "heatmap") & (table.alpha == 1.0)].iloc[0]
    assert (row.holds, row.violated) == (0, 2)
    assert np.isnan(row.time_holds_mean) and row.time_violated_mean == pytest.approx(0.1)
    assert row.pb_violated == 0 and row.pb_unknown + row.pb_holds == 2
    row = table[(table.tolerance_units == "heatmap") & (table.alpha == 1.5)].iloc[0]
    assert row.time_holds_mean == pytest.approx(30.0) and np.isnan(row.time_violated_mean)
    assert np.isnan(row.time_unknown_mean)
    pb = table[(table.tolerance_units == "heatmap") & table.overlapping].iloc[0]
    assert pb.pb_time_unknown_mean == pytest.approx(200.0) and np.isnan(pb.pb_time_holds_mean)


def test_method_cells_has_every_method(table):
    cells = comparison.method_cells(table)
    methods = cells.groupby("model")["method"].unique()
    for model in ("cnn", "cnn_patch"):
        assert list(methods[model]) == ["alloc (heatmap)", "alloc (paper)", "pb"]
    pb = cells[(cells.method == "pb") & (cells.model == "cnn")]
    assert len(pb) == 8  # 2 overlap classes × 2 κ × 2 α
    assert pb[pb.overlapping].rate.eq(0.0).all() and pb[~pb.overlapping].rate.eq(1.0).all()
    assert pb[~pb.overlapping].time_proof.eq(50.0).all()
    assert pb[pb.overlapping].time_proof.isna().all()  # no proof: no proof time, not 0
    paper = tables.PAPER_T_LOCAL[(2, True, 1.5, 1.0)]
    cell = cells[(cells.method == "alloc (paper)") & cells.overlapping & (cells.kappa == 1.5)]
    assert cell[cell.alpha == 1.0].paper_rate.iloc[0] == paper[2]
    # The paper's 13.1 % over 200 seeds: 26 / 200.
    row = cell[cell.alpha == 1.0].iloc[0]
    assert (row.paper_rate_lo, row.paper_rate_hi) == pytest.approx(wilson(26, 200), abs=1e-9)
    # Ours: 0 of 2 and 2 of 2 seeds inside Ξ.
    assert (pb[pb.overlapping].rate_lo.iloc[0], pb[pb.overlapping].rate_hi.iloc[0]) == (
        pytest.approx((0.0, 0.6576198), abs=1e-6)
    )
    assert pb[~pb.overlapping].rate_lo.iloc[0] == pytest.approx(1 - 0.6576198, abs=1e-6)
    assert pb[~pb.overlapping].rate_hi.iloc[0] == 1.0


def test_method_cells_carry_the_times_median_and_quartiles():
    records = local_records().query("model == 'cnn'").copy()
    # Seed 0 a slow proof of 100 s in every allocation cell of α = 1.5: 30 and 100 s.
    slow = (records.alpha == 1.5) & (records.image_id == 0)
    records.loc[slow, "time"] = 100.0
    records = pd.concat([records, records[slow].assign(image_id=2, time=10.0)])
    cells = comparison.method_cells(tables.t_local(records))
    heat = cells[(cells.method == "alloc (heatmap)") & (cells.alpha == 1.5)].iloc[0]
    # 10, 30, 100 s: median 30, quartiles 20 and 65 (linear between the order statistics).
    assert (heat.time_median, heat.time_q1, heat.time_q3) == (30.0, 20.0, 65.0)
    assert heat.time_all == pytest.approx(140 / 3) and heat.timed == 3
    assert heat.time_std == pytest.approx(np.std([10.0, 30.0, 100.0]))
    pb = cells[(cells.method == "pb") & cells.overlapping & (cells.alpha == 1.5)].iloc[0]
    assert (pb.time_median, pb.timed) == (200.0, 3)


def test_compact_table_counts_rates_and_times(table):
    compact = comparison.compact_table(table)
    assert list(compact.columns) == [
        "model", "method", "instances", "holds", "violated", "unknown", "not_certifiable",
        "fewest_seeds", "cells", "rate", "rate_lo", "rate_hi", "paper_rate", "paper_rate_lo",
        "paper_rate_hi", "delta", "proof_s", "refutation_s", "median_low_s", "median_high_s",
        "paper_s",
    ]  # fmt: skip
    assert len(compact) == 6
    row = compact.set_index(["model", "method"]).loc[("cnn", "alloc (heatmap)")]
    assert (row.holds, row.violated, row.unknown, row.cells) == (8, 8, 0, 8)
    assert (row.not_certifiable, row.fewest_seeds) == (0, 2)
    assert row.rate == pytest.approx(0.5) and row.proof_s == pytest.approx(30.0)
    assert (row.rate_lo, row.rate_hi) == pytest.approx((0.2799956, 0.7200044), abs=1e-6)  # 8/16
    assert row.refutation_s == pytest.approx(0.1)
    assert (row.median_low_s, row.median_high_s) == (0.1, 30.0)
    paper = [v[2] for k, v in tables.PAPER_T_LOCAL.items() if k[0] == 2]
    assert row.paper_rate == pytest.approx(np.mean(paper))
    # The paper's 8 cells of 200 seeds: 780.4 → 780 of 1600.
    assert (row.paper_rate_lo, row.paper_rate_hi) == pytest.approx(wilson(780, 1600), abs=1e-9)
    assert row.delta == pytest.approx(0.5 - np.mean(paper))
    pb = compact.set_index(["model", "method"]).loc[("cnn", "pb")]
    assert (pb.holds, pb.unknown, pb.proof_s) == (8, 8, 50.0) and np.isnan(pb.refutation_s)


def _texts(ax) -> list[str]:
    return [t.get_text() for t in ax.texts]


def test_figure_shows_every_method_beside_the_paper(table):
    fig = comparison.plot_comparison(table, "T-local", hardware="2 CPU cores")
    assert isinstance(fig, Figure)
    titles = [ax.get_title() for ax in fig.axes]
    for model in ("cnn", "cnn_patch"):
        for method in ("alloc (heatmap)", "alloc (paper)", "pb"):
            assert any(t.startswith(f"{model}: {method}\n") for t in titles), (model, method)
    assert sum(t.startswith("paper (RTX A4000)") for t in titles) == 2
    # Records from before pb_rule: every pb holds rests on the linearised bound.
    assert any(
        t.startswith("cnn: pb\nholds/violated/unknown 8/0/8\n(holds: 0 exact, 8 linearised bound)")
        for t in titles
    )
    assert "cnn: alloc (heatmap)\nholds/violated/unknown 8/8/0" in titles
    time_axes = [ax for ax in fig.axes if ax.get_yscale() == "log"]
    assert len(time_axes) == 2
    assert all("ours: 2 CPU cores" in ax.get_title() and "RTX A4000" in ax.get_title()
               for ax in time_axes)  # fmt: skip
    # Our cell at (apart, κ = 1, α = 1) under the 'heatmap' reading: 0 of 2 (Wilson 0–66 %)
    # against 55 % of 200 (48–62 %).
    heat = next(ax for ax in fig.axes if ax.get_title().startswith("cnn: alloc (heatmap)"))
    assert "ours 0% (0–66)\npaper 55% (48–62)\nΔ -55 pp" in _texts(heat)
    paper_grid = next(ax for ax in fig.axes if ax.get_title().startswith("paper"))
    assert "55%\n(48–62)" in _texts(paper_grid)
    assert heat.get_yticklabels()[0].get_text() == "m=2 apart"
    assert [t.get_text() for t in heat.get_xticklabels()][:2] == ["κ=1\nα=1", "κ=1\nα=1.5"]
    # The same colour scale in every grid.
    limits = {im.get_clim() for ax in fig.axes for im in ax.images}
    assert limits == {(0.0, 1.0)}
    labels = time_axes[0].get_legend_handles_labels()[1]
    assert "pb: proofs (holds)" in labels and "alloc (heatmap): refutations (violated)" in labels
    assert "pb: unknown (budget spent)" in labels  # pb's overlapping hulls, 200 s each
    assert "alloc (heatmap): median and quartiles, all instances" in labels
    assert any(label.startswith("paper (RTX A4000)") for label in labels)
    # Proof times on the axis: 30 s for the allocation's holds, 50 s for pb.
    offsets = np.concatenate([c.get_offsets()[:, 1] for c in time_axes[0].collections
                              if len(c.get_offsets())])  # fmt: skip
    assert {30.0, 50.0, 0.1, 200.0} <= set(np.round(offsets.compressed(), 6))


def test_missing_cells_are_hatched_not_zero():
    records = local_records()
    # No seed of (overlapping, κ = 1.5, α = 1.5) inside Ξ; no paper cell for m = 5.
    hit = records.overlapping & (records.kappa == 1.5) & (records.alpha == 1.5)
    records.loc[hit, "seed_inside"] = False
    extra = records[records.m == 2].head(1).assign(m=5)
    table = tables.t_local(pd.concat([records, extra], ignore_index=True))
    fig = comparison.plot_comparison(table, "T-local")
    heat = next(ax for ax in fig.axes if ax.get_title().startswith("cnn: alloc (heatmap)"))
    texts = _texts(heat)
    assert "no seed\nin Ξ" in texts and "no data" in texts
    assert any(t.endswith("paper –") for t in texts)
    (image,) = heat.images
    values = image.get_array()
    assert values.mask.sum() == texts.count("no data") + texts.count("no seed\nin Ξ")
    assert any(p.get_hatch() == "///" for p in heat.patches)
    paper = next(ax for ax in fig.axes if ax.get_title().startswith("paper"))
    assert "no cell" in _texts(paper)


def test_old_tables_still_render():
    """A table from before the readings, the pose-bound method and the time split, as
    read back from its CSV: one method, times over all instances."""
    records = local_records(pose_bound=False).drop(columns=["model", "tolerance_units"])
    table = tables.t_local(records)
    old = table.drop(columns=["time_holds_mean", "time_violated_mean"])
    old = pd.read_csv(io.StringIO(old.to_csv(index=False)))
    cells = comparison.method_cells(old)
    assert list(cells.method.unique()) == ["alloc"] and (cells.model == "").all()
    fig = comparison.plot_comparison(old, "old")
    (time_ax,) = [ax for ax in fig.axes if ax.get_yscale() == "log"]
    labels = time_ax.get_legend_handles_labels()[1]
    assert labels[0] == "alloc: all instances (table without the split)"
    # Older still: no medians or quartiles, no intervals stored (method_cells makes them).
    oldest = old.drop(
        columns=[c for c in old if c.endswith(("_lo", "_hi", "_q1", "_q3", "_median"))]
    )
    cells = comparison.method_cells(oldest)
    assert cells.time_median.isna().all() and cells.rate_lo.notna().all()
    (time_ax,) = [
        ax for ax in comparison.plot_comparison(oldest, "oldest").axes if ax.get_yscale() == "log"
    ]
    assert not any("median" in lab for lab in time_ax.get_legend_handles_labels()[1])
    compact = comparison.compact_table(old)
    assert len(compact) == 1 and np.isnan(compact.proof_s.iloc[0])
    # Older still: no pb_violated / pb_unknown columns beside pb_holds.
    with_pb = tables.t_local(local_records().query("model == 'cnn'"))
    older = with_pb.drop(columns=["pb_violated", "pb_unknown", "pb_time_holds_mean"])
    counts = comparison.compact_table(older).set_index("method").loc["pb"]
    assert counts.holds == 8 and pd.isna(counts.violated) and pd.isna(counts.unknown)
    fig = comparison.plot_comparison(older, "older")
    assert any(
        ax.get_title().startswith(
            "cnn: pb\nholds/violated/unknown 8/?/?\n(holds: 0 exact, 8 linearised bound)"
        )
        for ax in fig.axes
    )


def test_bad_input():
    with pytest.raises(ValueError, match="^table: expected a verification table"):
        comparison.method_cells(pd.DataFrame({"alpha": [1.0]}))
    with pytest.raises(ValueError, match="^table: expected a pandas DataFrame"):
        comparison.plot_comparison([1, 2], "x")
    with pytest.raises(ValueError, match="^title"):
        comparison.plot_comparison(tables.t_local(local_records()), None)
    with pytest.raises(ValueError, match="^table_csv"):
        comparison.save_comparison("/nonexistent/t_local.csv", "/tmp/x.png")


def test_pose_bound_holds_say_which_are_exact():
    records = local_records()
    exact = (records.pb_status == "holds") & (records.kappa == 1.0)
    records["pb_rule"] = np.where(exact, "enumeration", "linearised")
    cells = comparison.method_cells(tables.t_local(records))
    pb = cells[(cells.method == "pb") & (cells.model == "cnn")]
    assert pb.exact_holds.sum() == 4 and pb.holds.sum() == 8
    assert cells[cells.method != "pb"].exact_holds.isna().all()
    fig = comparison.plot_comparison(tables.t_local(records), "T-local")
    titles = [ax.get_title() for ax in fig.axes]
    assert any(
        t.startswith("cnn: pb\nholds/violated/unknown 8/0/8\n(holds: 4 exact, 4 linearised bound)")
        for t in titles
    )


def test_pose_bound_rate_counts_seeds_whose_argmax_pose_is_inside():
    records = local_records().query("model == 'cnn'")
    heatmap = records.tolerance_units == "heatmap"
    # The argmax pipeline's pose leaves Ξ at image 1's seed: pb's denominator drops it.
    records = records.assign(pb_seed_inside=np.where(heatmap, records.image_id == 0, np.nan))
    table = tables.t_local(records)
    cells = comparison.method_cells(table)
    pb = cells[cells.method == "pb"]
    assert (pb.seeds_inside == 1).all()
    assert (cells[cells.method == "alloc (heatmap)"].seeds_inside == 2).all()
    fig = comparison.plot_comparison(table, "T-local")
    (title,) = [ax.get_title() for ax in fig.axes if ax.get_title().startswith("cnn: pb")]
    assert title.endswith("\nrate among seeds whose argmax pose is in Ξ")


def test_intervals_compare_as_cells_and_quartiles_as_timing(tmp_path):
    """Two runs of the same records: the intervals are numbers of the table (the same
    counts give the same bytes), the medians and quartiles timing columns (aside)."""
    records = local_records()
    slower = records.assign(time=records.time * 3, pb_time=records.pb_time * 3)
    fewer = records.assign(seed_inside=records.image_id == 0)
    for run, frame in (("a", records), ("b", slower), ("c", fewer)):
        write_table(tables.t_local(frame), tmp_path / run / "tables" / "t_local")
    assert compare_results(tmp_path / "a", tmp_path / "b") == {"tables/t_local.csv": "same"}
    differs = compare_results(tmp_path / "a", tmp_path / "c")["tables/t_local.csv"]
    assert "verified_rate_lo" in differs and "verified_rate_hi" in differs
    assert "time_median" not in differs and "paper_rate_lo" not in differs


def _run(root, records: pd.DataFrame):
    """A results folder holding T-local of ``records`` and the records' CSV."""
    write_table(tables.t_local(records), root / "tables" / "t_local")
    records.to_csv(root / "tables" / "t_local_records.csv", index=False)
    return root


def test_compare_names_the_cells_where_a_time_cap_ended_a_search(tmp_path):
    """A cap that fired in one run only is named, per file, after the cells that differ;
    without a fired cap nothing is named."""
    records = local_records().query("model == 'cnn'").reset_index(drop=True)
    records["stopped"] = "nodes"
    records["pb_stopped"] = np.where(records.tolerance_units == "heatmap", "nodes", None)
    at = (
        (records.tolerance_units == "heatmap") & ~records.overlapping
        & (records.kappa == 1.0) & (records.alpha == 1.5) & (records.image_id == 0)
    )  # fmt: skip
    assert at.sum() == 1
    # Run b: the allocation method's search of that instance capped before its budget
    # (unknown, not holds); the pose-bound method's of the same instance capped too, with
    # its verdict unchanged.
    capped = records.copy()
    capped.loc[at, ["status", "stopped", "pb_stopped"]] = ["unknown", "time", "time"]
    a, b = _run(tmp_path / "a", records), _run(tmp_path / "b", capped)
    found = compare_results(a, b)
    cell = "cnn heatmap α=1.5 κ=1 m=2 non-overlapping"
    instance = "cnn heatmap objects image 0 α=1.5 κ=1 m=2 non-overlapping"
    caps = "; time cap fired (not the node budget: the verdict depends on the machine's speed)"
    assert found["tables/t_local_records.csv"] == (
        "cells differ: status (1), stopped (1), pb_stopped (1)"
        f"{caps} in b only: {instance} [alloc], {instance} [pb]; "
        "rows that differ with no cap fired in either run: 0 of 1"
    )
    table = found["tables/t_local.csv"]
    assert table.startswith("cells differ: holds (1), unknown (1), ")
    assert table.endswith(
        f"{caps} in b only: {cell} [alloc], {cell} [pb]; "
        "rows that differ with no cap fired in either run: 0 of 1"
    )
    assert compare_results(b, a)["tables/t_local.csv"].endswith(
        f"in a only: {cell} [alloc], {cell} [pb]; "
        "rows that differ with no cap fired in either run: 0 of 1"
    )
    # Another instance differs as well, without a cap: counted apart.
    other = capped.copy()
    other.loc[other.index[~at][0], "status"] = "unknown"
    found = compare_results(a, _run(tmp_path / "c", other))
    assert found["tables/t_local_records.csv"].endswith(
        f"in b only: {instance} [alloc], {instance} [pb]; "
        "rows that differ with no cap fired in either run: 1 of 2"
    )
    # The cap fired in both runs, one of them elsewhere too: named by run.
    both = capped.copy()
    both.loc[~at & (both.tolerance_units == "paper"), "stopped"] = "time"
    found = compare_results(b, _run(tmp_path / "d", both))["tables/t_local.csv"]
    assert "in b only: cnn paper α=1 κ=1 m=2 non-overlapping [alloc] ×2, " in found
    assert f"in both runs: {cell} [alloc], {cell} [pb]" in found
    # No cap in either run: what differs, nothing named.
    changed = records.copy()
    changed.loc[at, "status"] = "unknown"
    found = compare_results(a, _run(tmp_path / "e", changed))
    assert found == {
        "tables/t_local.csv": "cells differ: holds (1), unknown (1), verified_rate (1), "
        "verified_rate_lo (1), verified_rate_hi (1), decided (1), pb_only (1)",
        "tables/t_local_records.csv": "cells differ: status (1)",
    }
    # The same records: the same tables, whatever the caps.
    assert set(compare_results(b, _run(tmp_path / "f", capped)).values()) == {"same"}


def test_capped_searches_reads_tables_and_records_as_stored_and_from_csv():
    records = pd.DataFrame(
        {
            "kind": "contrast",
            "level": 5e-4,
            "image_id": [0, 1, 2],
            "kappa": 1.0,
            "alpha": 1.0,
            "status": ["holds", "unknown", "unknown"],
            "time": 1.0,
            "seed_inside": True,
            "stopped": ["nodes", "time", "time"],
            "pb_status": ["holds", "unknown", "holds"],
            "pb_time": 1.0,
            "pb_stopped": ["witness", "time", None],
            "pb_nonlinear": [[1.0] * 6] * 3,
        }
    )
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        assert comparison.capped_searches(frame) == {
            "contrast image 1 α=1 κ=1 level=0.0005 [alloc]": 1,
            "contrast image 2 α=1 κ=1 level=0.0005 [alloc]": 1,
            "contrast image 1 α=1 κ=1 level=0.0005 [pb]": 1,
        }
        table = tables.summarise(frame, ["kind", "level", "kappa", "alpha"])
        assert comparison.capped_searches(table) == {
            "contrast α=1 κ=1 level=0.0005 [alloc]": 2,
            "contrast α=1 κ=1 level=0.0005 [pb]": 1,
        }
    # Neither a table nor records (no κ, α), or no cap fired: nothing.
    assert comparison.capped_searches(records.drop(columns=["kappa"])) == {}
    assert comparison.capped_searches(records.assign(stopped="nodes", pb_stopped=None)) == {}
    assert comparison.time_caps(records.iloc[:1], records.iloc[:1]) == ""
