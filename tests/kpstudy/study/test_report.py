"""kpstudy.study.report: REPORT.md from stored tables, old ones included."""

import numpy as np
import pandas as pd
import pytest

from kpstudy.io import save_figure, write_table
from kpstudy.study import comparison, report, tables
from tests.helpers.records import local_records


def _results(tmp_path, table: pd.DataFrame, name: str = "t_local", figure: bool = True):
    out = tmp_path / "quick"
    write_table(table, out / "tables" / name)
    if figure:
        save_figure(comparison.plot_comparison(table, name), out / "figures" / f"{name}.png")
    return out


def test_report_shows_figure_compact_table_and_links(tmp_path):
    table = tables.t_local(local_records())
    out = _results(tmp_path, table)
    text = report.write_report(out).read_text()
    assert "![t_local](figures/t_local.png)" in text
    assert text.count("figures/t_local.png") == 1  # not drawn twice
    assert "[tables/t_local.csv](tables/t_local.csv)" in text
    assert (
        "| model | method | instances | holds / violated / unknown / not certifiable | cells "
        "| verified rate (95 % CI) | paper (95 % CI) |"
    ) in text
    # cnn, alloc (heatmap): 8 holds, 8 refutations; 8 of 16 seeds over 8 cells (Wilson
    # 28–72 %); 30 s proofs, 0.1 s refutations, cell medians 0.1 s (α = 1) and 30 s
    # (α = 1.5); the paper's mean over the m = 2 cells (48.8 %, 1600 seeds: 46–51 %).
    paper = np.mean([v[2] for k, v in tables.PAPER_T_LOCAL.items() if k[0] == 2])
    paper_s = np.mean([v[0] for k, v in tables.PAPER_T_LOCAL.items() if k[0] == 2])
    row = (
        f"| cnn | alloc (heatmap) | 16 | 8 / 8 / 0 / 0 | 8 | 50% (28–72) | {paper:.0%} (46–51) | "
        f"{100 * (0.5 - paper):+.0f} pp | 30 | 0.1 | 0.1–30 | {paper_s:.3g} |"
    )
    assert row in text
    assert "| cnn_patch | pb | 16 | 8 / 0 / 8 / – | 8 | 50% (28–72) |" in text
    assert "<details><summary>Full table <code>t_local</code>" in text
    assert (out / "tables" / "t_local.md").read_text().strip() in text
    assert "*Figure `t_local_pose_bound` is missing.*" in text


def test_readings_test_the_papers_trends_on_the_numbers(tmp_path):
    table = tables.t_local(local_records())
    trends_ = report.trend_readings("t_local", table).T  # m = 2 only: no trend in m
    assert list(trends_.columns) == [
        "Verified rate rises with α",
        "Verified rate falls with κ",
        "Time per instance falls with α",
        "Time per instance rises with κ",
        "Overlapping hulls cost more time",
    ]
    assert list(trends_.index) == [
        "the paper's numbers",
        *(
            f"{model} {method}"
            for model in ("cnn", "cnn_patch")
            for method in ("alloc (heatmap)", "alloc (paper)", "pb")
        ),
    ]
    rate = trends_["Verified rate rises with α"]
    # The paper's m = 2 cells rise with α in all 4 pairs (overlap × κ), by 34 pp on average:
    # over 200 seeds a cell, significant.
    assert rate["the paper's numbers"] == "shown (p < 0.001): 4 of 4 (+34 pp)"
    # Ours: the 'heatmap' reading holds only at α = 1.5 (+100 pp: 0 of 8 against 8 of 8,
    # significant even so); the 'paper' one always. 2 seeds a cell: a smoke test.
    smoke = "smoke test, 2 per cell"
    assert rate["cnn alloc (heatmap)"] == f"shown (p < 0.001; {smoke}): 4 of 4 (+100 pp)"
    assert rate["cnn alloc (paper)"] == f"not shown (p = 1; {smoke}): 0 of 4, 4 unchanged (+0 pp)"
    cost = trends_["Overlapping hulls cost more time"]
    assert cost["cnn pb"] == f"shown (p < 0.001; {smoke}): 4 of 4 (+150 s)"  # 200 s against 50
    # Refutations at α = 1 (0.1 s), proofs at α = 1.5 (30 s): time rises, against the paper.
    assert trends_.loc["cnn alloc (heatmap)", "Time per instance falls with α"] == (
        f"contradicted (p < 0.001; {smoke}): 0 of 4, 4 against (+29.9 s)"
    )
    text = report.write_report(_results(tmp_path, table)).read_text()
    assert "| the paper states | the paper's numbers | cnn alloc (heatmap) |" in text
    assert (
        "| *Verified rate rises with α* | shown (p < 0.001): 4 of 4 (+34 pp) | "
        f"shown (p < 0.001; {smoke}): 4 of 4 (+100 pp) |"
    ) in text
    assert "*shown* when they differ significantly in the paper's direction" in text


def test_t_prob_reading_says_whether_soundness_rises_with_kappa():
    prob = pd.DataFrame(
        {
            "tolerance_units": ["heatmap"] * 4 + ["paper"] * 4,
            "kappa": [1.0, 1.0, 2.0, 2.0] * 2,
            "alpha": [1.0, 2.0] * 4,
            "soundness": [0.9, 0.95, 0.85, 0.97, 0.9, 0.9, 0.95, 0.95],
            "completeness": [0.1, 0.2, 0.05, 0.1] * 2,
            "samples": 200,
        }
    )
    trends_ = report.trend_readings("t_prob", tables.t_prob(prob)).T
    assert list(trends_.columns) == [
        "Soundness rises with κ",
        "Soundness falls with α",
        "Completeness falls with κ",
    ]
    column = trends_["Soundness rises with κ"]
    # The paper: 0.998978 → 1.0 at α = 1, 0.988339 → 0.999999 at α = 2, over its 3000 × 5000
    # samples a cell.
    assert column["the paper's numbers"] == "shown (p < 0.001): 2 of 2 (+0.63 pp)"
    # Ours over 200 samples a cell: 370 of 400 at κ = 1 against 364 of 400 at κ = 2.
    assert column["ours, 'heatmap' reading"].startswith("not shown (p = 0.")
    assert column["ours, 'heatmap' reading"].endswith(": 1 of 2, 1 against (-1.5 pp)")
    assert column["ours, 'paper' reading"] == "shown (p = 0.01): 2 of 2 (+5 pp)"
    # The paper: soundness falls with α (0.998978 → 0.988339 at κ = 1, 1 → 0.999999 at 2).
    falls = trends_["Soundness falls with α"]
    assert falls["the paper's numbers"].startswith("shown (p < 0.001): 2 of 2")
    # Ours: 350 of 400 at α = 1 against 384 of 400 at α = 2: significantly against.
    assert falls["ours, 'heatmap' reading"] == (
        "contradicted (p < 0.001): 0 of 2, 2 against (+8.5 pp)"
    )
    without = report.trend_readings("t_prob", tables.t_prob(prob.drop(columns="samples")))
    assert without.loc["Soundness falls with α", "ours, 'heatmap' reading"].startswith(
        "cannot tell (no counts to test)"
    )
    single = tables.t_prob(prob[prob.tolerance_units == "paper"].drop(columns="tolerance_units"))
    assert list(report.trend_readings("t_prob", single).columns) == [
        "the paper's numbers",
        "ours",
    ]


def test_old_results_folders_still_render(tmp_path):
    """Tables from before the readings, the pose-bound method and the time split (read
    back from CSV), without their figure: the report lists the figure as missing and
    still gives the compact table and the readings."""
    records = local_records(pose_bound=False)
    records = records.query("model == 'cnn' and tolerance_units == 'heatmap'")
    records = records.drop(columns=["model", "tolerance_units"])
    old = tables.t_local(records).drop(columns=["time_holds_mean", "time_violated_mean"])
    out = _results(tmp_path, old, figure=False)
    text = report.write_report(out).read_text()
    assert "*Figure `t_local` is missing.*" in text
    assert "| – | alloc | 16 | 8 / 8 / 0 / 0 | 8 | 50% (28–72) |" in text
    assert text.split("| – | alloc |")[1].split("\n")[0].endswith("| – | – | 0.1–30 | 62.2 |")
    assert (
        "| *Verified rate rises with α* | shown (p < 0.001): 4 of 4 (+34 pp) | "
        "shown (p < 0.001; smoke test, 2 per cell): 4 of 4 (+100 pp) |"
    ) in text
    # With a figure drawn from the old table: proof times absent, all-instance times shown.
    fig = comparison.plot_comparison(pd.read_csv(out / "tables" / "t_local.csv"), "old")
    assert fig.axes


def test_missing_tables_are_listed(tmp_path):
    text = report.write_report(tmp_path / "empty").read_text()
    for name in ("t_local", "t_global", "t_resnet", "t_prob", "f_sym"):
        assert f"*Table `{name}` is missing (its notebook has not run).*" in text


def test_a_table_of_few_seeds_is_called_a_smoke_test(tmp_path):
    table = tables.t_local(local_records())  # 2 seeds a cell
    (line,) = report.smoke_test_reading(table)
    assert line.startswith("**Smoke test.** A cell has as few as 2 seeds inside Ξ (at most 2;")
    text = report.write_report(_results(tmp_path, table)).read_text()
    assert "- **Smoke test.**" in text
    title = comparison.plot_comparison(table, "T-local").get_suptitle()
    assert "smoke test: as few as 2 seeds inside Ξ in a cell (fewer than 20)" in title
    # 20 seeds a cell (10 images × 2 copies): a result, not a smoke test.
    records = local_records()
    many = pd.concat([records.assign(image_id=records.image_id + 2 * i) for i in range(10)])
    assert report.smoke_test_reading(tables.t_local(many)) == []
    assert "smoke" not in comparison.plot_comparison(tables.t_local(many), "x").get_suptitle()
    # Seeds outside Ξ do not count: 20 instances a cell, 19 of them inside.
    outside = many.assign(seed_inside=many.image_id != 0)
    (line,) = report.smoke_test_reading(tables.t_local(outside))
    assert "as few as 19 seeds inside Ξ (at most 19;" in line


def test_readings_say_where_our_intervals_and_the_papers_overlap():
    records = local_records().query("model == 'cnn'")
    lines = report.interval_readings(tables.t_local(records))
    assert [line.split(":")[0] for line in lines] == [
        "`cnn` alloc (heatmap)",
        "`cnn` alloc (paper)",
        "`cnn` pb",
    ]
    # 'heatmap': 0 of 2 (0–66 %) at α = 1 and 2 of 2 (34–100 %) at α = 1.5, each overlapping
    # the paper's (200 seeds: e.g. 55 % → 48–62 %).
    assert lines[0] == (
        "`cnn` alloc (heatmap): our 95% interval of the verified rate overlaps the paper's in "
        "8 of 8 cells."
    )
    # 'paper': 2 of 2 everywhere (34–100 %); the paper's κ = 1.5, α = 1 cells are 16.9 %
    # (12–23 %) and 13.1 % (9–18 %): ours lies above them.
    assert lines[1].startswith(
        "`cnn` alloc (paper): our 95% interval of the verified rate overlaps the paper's in "
        "6 of 8 cells; ours lies wholly above the paper's in 2: "
        "m=2 apart κ=1.5 α=1: 34–100 % against 12–23 %; "
        "m=2 overlapping κ=1.5 α=1: 34–100 % against 9–18 %."
    )
    # pb: 0 of 2 when overlapping: below the paper's 74.1 % (68–80 %) at κ = 1, α = 1.5.
    assert (
        "ours lies wholly below the paper's in 1: m=2 overlapping κ=1 α=1.5: 0–66 % " in (lines[2])
    )


def _not_certifiable(records: pd.DataFrame) -> pd.DataFrame:
    """``records`` with seed 1 not certifiable at α = 1 (both κ) and at α = 1.5, κ = 1.5
    only: the pixel grid exceeds ε / κ. Its cells are float half-widths, as new records
    store them, and it has no dv of its own."""
    records = records.copy()
    records["dv"] = [[[0.5, 1.0]] * 23] * len(records)
    grid = (records.alpha == 1.0) | (records.kappa == 1.5)
    hit = (records.image_id == 1) & grid
    records.loc[hit, "status"] = "not_certifiable"
    records.loc[hit, "counterexample"] = None
    records["dv"] = [None if h else v for h, v in zip(hit, records["dv"])]
    return records


def test_not_certifiable_counts_in_its_own_column_and_the_report_says_per_alpha(tmp_path):
    records = _not_certifiable(local_records().query("model == 'cnn'"))
    table = tables.t_local(records)
    heat = table[table.tolerance_units == "heatmap"].set_index(["overlapping", "kappa", "alpha"])
    cell = heat.loc[(False, 1.0, 1.0)]
    # Seed 0 violated, seed 1 not certifiable: both inside Ξ, neither verified.
    assert (cell.holds, cell.violated, cell.not_certifiable, cell.seeds_inside) == (0, 1, 1, 2)
    assert cell.verified_rate == 0.0 and cell.decided == 0.5
    cell = heat.loc[(False, 1.0, 1.5)]  # κ = 1, α = 1.5: both hold
    assert (cell.holds, cell.not_certifiable, cell.verified_rate) == (2, 0, 1.0)
    cell = heat.loc[(False, 1.5, 1.5)]  # seed 1 ruled out: 1 of the 2 seeds inside
    assert (cell.holds, cell.not_certifiable, cell.verified_rate) == (1, 1, 0.5)
    assert cell.dv_mean == pytest.approx(0.75) and cell.dv_zero == 0.0  # seed 0's floats
    lines = report.campaign_summary(table[table.tolerance_units == "heatmap"])
    # Seed 1 in the 4 (overlapping × κ) cells of α = 1 and the 2 of α = 1.5, κ = 1.5.
    assert "6 holds, 4 violated" in lines[0]
    assert "6 not certifiable at the heatmap's resolution" in lines[0]
    (line,) = [s for s in lines if s.startswith("The pixel grid alone")]
    assert "no cell of the 64×64 heatmaps of `cnn` certifies the seed" in line
    # α = 1: 2 of 4 per κ (2 hulls × 2 seeds), 4 of 8 in all; α = 1.5: κ = 1.5 only.
    assert line.endswith(
        "α = 1: 50% (κ = 1: 50%, κ = 1.5: 50%); α = 1.5: 25% (κ = 1: 0%, κ = 1.5: 50%) of "
        "the seeds."
    )
    # Only the sound reading refuses a seed for its pixel grid: no sentence for 'paper'.
    assert report.not_certifiable_reading(table[table.tolerance_units == "paper"]) == []
    compact = comparison.compact_table(table).set_index("method")
    assert compact.loc["alloc (heatmap)", "not_certifiable"] == 6
    assert compact.loc["alloc (paper)", "not_certifiable"] == 6
    assert pd.isna(compact.loc["pb", "not_certifiable"])
    text = report.write_report(_results(tmp_path, table)).read_text()
    assert "| cnn | alloc (heatmap) | 16 | 6 / 4 / 0 / 6 |" in text
    assert "| cnn | pb | 16 | 8 / 0 / 8 / – |" in text
    fig = comparison.plot_comparison(table, "T-local")
    titles = [ax.get_title() for ax in fig.axes]
    assert any(
        t.startswith("cnn: alloc (heatmap)\nholds/violated/unknown 6/4/0\n")
        and "not certifiable (pixel grid > ε): 6" in t
        for t in titles
    )


def test_the_resnet_reading_names_its_256_pixel_heatmaps():
    records = pd.DataFrame(
        [
            dict(
                model="resnet18",
                kind="blocks",
                overlapping=o,
                kappa=1.0,
                alpha=1.5,
                image_id=i,
                status="not_certifiable" if i < 3 else "holds",
                time=1.0,
                seed_inside=True,
                dv=None if i < 3 else [[1.5, 2.0]] * 23,
            )
            for o in (False, True)
            for i in range(4)
        ]  # fmt: skip
    )
    table = tables.t_resnet(records)
    assert list(table.not_certifiable) == [3, 3] and list(table.verified_rate) == [0.25, 0.25]
    (line,) = [s for s in report.campaign_summary(table) if s.startswith("The pixel grid")]
    assert "256×256 heatmaps of `resnet18`" in line and line.endswith("α = 1.5: 75% of the seeds.")


def _with_errors(records: pd.DataFrame, rows, text="ValueError: keypoint 0 outside the image"):
    """``records`` with the rows at positions ``rows`` turned into ``error`` records: the
    error text, no certificate."""
    records = records.copy().reset_index(drop=True)
    records["error"] = None
    records.loc[rows, "status"] = "error"
    records.loc[rows, "error"] = text
    for column in ("time", "seed_inside", "counterexample", "dv", "pb_status", "pb_time"):
        records[column] = records[column].astype(object)
        records.loc[rows, column] = None
    return records


def _campaign_results(tmp_path, records: pd.DataFrame, name: str = "t_local"):
    """A results folder with table ``name`` of ``records`` and the records' CSV."""
    out = _results(tmp_path, getattr(tables, name)(records), name, figure=False)
    records.to_csv(out / "tables" / f"{name}_records.csv", index=False)
    return out


def test_the_report_lists_the_instances_that_ended_error(tmp_path, capsys):
    records = local_records().query("model == 'cnn'").reset_index(drop=True)
    first = records.index[
        (records.tolerance_units == "heatmap") & records.overlapping & (records.alpha == 1.5)
    ][0]
    records = _with_errors(records, [first], "RuntimeError: a `bad` | value\nsecond line")
    out = _campaign_results(tmp_path, records)
    row = records.loc[first]
    label = f"cnn heatmap objects image {row.image_id} α=1.5 κ={row.kappa:g} m=2 overlapping"
    assert report.error_instances(out) == {
        "t_local": (32, [(label, "RuntimeError: a `bad` | value\nsecond line")])
    }
    text = report.write_report(out).read_text()
    section = text.split("**Instances that could not be run.**")[1]
    assert section.startswith(
        " 1 of the 32 records of [tables/t_local_records.csv](tables/t_local_records.csv) "
        "ended `error`"
    )
    # One bullet: the instance and its error on one line, as code.
    assert f"\n- {label}: `` RuntimeError: a `bad` | value second line ``\n" in section
    assert text.index("**Instances that could not be run.**") < text.index("## T-global")
    # kpstudy reproduce lists the same instance from the same function.
    from kpstudy.study.campaign import InstanceErrors
    from kpstudy.study.reproduction import campaign_errors

    with pytest.raises(InstanceErrors, match="^1 of 32 campaign instances ended 'error'"):
        campaign_errors(out)
    assert f"[reproduce] error: t_local {label}: RuntimeError" in capsys.readouterr().out


def test_the_error_list_is_capped_and_counts_the_rest(tmp_path):
    records = local_records().query("model == 'cnn'")
    records = _with_errors(records, list(range(23)))  # 23 of 32
    text = report.write_report(_campaign_results(tmp_path, records)).read_text()
    section = text.split("**Instances that could not be run.**")[1].split("\n\n")[1]
    bullets = section.splitlines()
    assert len(bullets) == report.LISTED_ERRORS + 1 == 21
    assert all(b.endswith(": `ValueError: keypoint 0 outside the image`") for b in bullets[:20])
    assert bullets[-1].startswith("- and 3 more (every one: the rows of tables/t_local_records")
    # Without an error record, or without records, no such section.
    clean = _campaign_results(tmp_path / "clean", local_records().query("model == 'cnn'"))
    assert "Instances that could not be run" not in report.write_report(clean).read_text()
    assert report.error_instances(tmp_path / "none") == {}


def test_a_table_missing_its_markdown_still_lists_its_error_records(tmp_path):
    records = _with_errors(local_records().query("model == 'cnn'"), [0])
    out = _campaign_results(tmp_path, records)
    (out / "tables" / "t_local.md").unlink()
    text = report.write_report(out).read_text()
    assert "*Table `t_local` is missing" in text
    assert "1 of the 32 records of [tables/t_local_records.csv]" in text


def _capped(records: pd.DataFrame) -> pd.DataFrame:
    """``records`` with every search stopped by its node budget but two: the allocation
    method's of seed 0 at κ = 1, α = 1 (non-overlapping, both readings) and the pose-bound
    method's of seed 1 there, ended by the time cap."""
    records = records.copy()
    records["stopped"] = "nodes"
    records["pb_stopped"] = np.where(records.tolerance_units == "heatmap", "nodes", None)
    cell = (records.kappa == 1.0) & (records.alpha == 1.0) & ~records.overlapping
    records.loc[cell & (records.image_id == 0), "stopped"] = "time"
    pb = cell & (records.image_id == 1) & (records.tolerance_units == "heatmap")
    records.loc[pb, "pb_stopped"] = "time"
    return records


def test_the_report_counts_the_searches_a_time_cap_ended_per_method(tmp_path):
    records = local_records().query("model == 'cnn'")
    table = tables.t_local(_capped(records))
    text = report.write_report(_results(tmp_path, table, figure=False)).read_text()
    lines = [s for s in text.splitlines() if "time cap" in s]
    heat, paper = (
        next(s for s in lines if s.startswith(f"- `cnn`: '{u}' reading: "))
        for u in ("heatmap", "paper")
    )
    assert (
        "**Time caps.** The time cap, not the node budget, ended the search of 1 of the "
        "allocation method's and 1 of the pose-bound method's instances (α=1 κ=1 m=2 "
        "non-overlapping: allocation 1, pose-bound 1): those verdicts depend on "
        "the machine's speed"
    ) in heat
    assert "1 of the allocation method's instances (α=1 κ=1 m=2 non-overlapping: allocation 1)" in (
        paper
    )
    assert "pose-bound" not in paper  # the pose-bound method runs under the first reading only
    # No cap fired: said so, per method.
    table = tables.t_local(_capped(records).assign(stopped="nodes", pb_stopped="nodes"))
    (line,) = [s for s in report.campaign_summary(table) if "time cap" in s]
    assert line.startswith(
        "The time cap ended no search of the allocation method's or the pose-bound method's "
        "instances"
    )
    assert "do not depend on the machine's speed" in line


def test_the_report_opens_with_each_tables_cost_and_the_paper_profiles(tmp_path):
    out = tmp_path / "standard"
    (out / "tables").mkdir(parents=True)
    records = pd.DataFrame({"image_id": [1, 1, 2, 2, 3], "total_time": [360.0, 0, 720, 1800, 720]})
    records.to_csv(out / "tables" / "t_global_records.csv", index=False)
    pd.DataFrame({"image_id": [], "total_time": []}).to_csv(
        out / "tables" / "t_resnet_records.csv", index=False
    )
    cost = report.run_cost(out)
    assert list(cost.table) == ["t_global"]  # no records of t_local, none in t_resnet
    row = cost.iloc[0]
    assert (row.seeds, row.instances) == (3, 5)
    assert row.hours == pytest.approx(1.0) and row.median_s == 720
    assert row.paper_hours == pytest.approx(200 / 3)
    text = report.write_report(out).read_text()
    assert "| t_global | 3 | 5 | 1.00 | 720 | 66.7 | – |" in text  # memory not recorded
    # Records with each worker's peak memory: the table gives the largest.
    records.assign(peak_memory_mib=[900.0, 1200, 3072, 2000, 512]).to_csv(
        out / "tables" / "t_global_records.csv", index=False
    )
    assert report.run_cost(out).iloc[0].peak_gib == pytest.approx(3.0)
    assert "| t_global | 3 | 5 | 1.00 | 720 | 66.7 | 3.0 |" in report.write_report(out).read_text()
    assert "--profile paper --scheduler" in text
    assert report.cost_markdown(report.run_cost(tmp_path / "empty")) == []


def test_the_report_shows_what_each_search_had_decided_by_node_count(tmp_path):
    records = local_records()
    records["nodes"] = np.where(records.status == "holds", 3, 0)
    records["pb_nodes"] = np.where(records.pb_status == "holds", 40, 768)
    out = _campaign_results(tmp_path, records)
    text = report.write_report(out).read_text()
    header = "| model | reading | method | instances | ≤ 0 | ≤ 1 | ≤ 4 | ≤ 16 | ≤ 64 | ≤ 256 |"
    assert header + " ≤ 1024 | at its budget |" in text
    # 'heatmap': holds at α = 1.5 (3 nodes), violated at the seed elsewhere (0 nodes)
    assert "| cnn | heatmap | alloc | 16 | 50% | 50% | 100% | – | – | – | – | 100% |" in text
    # pb: holds where not overlapping (40 nodes), unknown at its 768 nodes where overlapping
    assert "| cnn | heatmap | pb | 16 | 0% | 0% | 0% | 0% | 50% | 50% | 50% | 50% |" in text
    assert report.budget_markdown(out / "tables" / "missing.csv") == []
