"""kpstudy.study.report and kpstudy.study.trends: REPORT.md from stored tables, old ones
included."""

import numpy as np
import pandas as pd
import pytest

from kpstudy.io import save_figure, write_table
from kpstudy.study import comparison, report, tables, trends
from tests.test_comparison import local_records


def _results(tmp_path, table: pd.DataFrame, name: str = "t_local", figure: bool = True):
    out = tmp_path / "quick"
    write_table(table, out / "tables" / name)
    if figure:
        save_figure(comparison.plot_comparison(table, name), out / "figures" / f"{name}.png")
    return out


def test_trend_counts_pairs_along_and_against():
    cells = pd.DataFrame(
        {
            "m": [2, 2, 3, 3, 4, 4],
            "alpha": [1.0, 1.5] * 3,
            "rate": [0.2, 0.5, 0.4, 0.1, 0.3, 0.3],
            "time_all": [10.0, 10.2, 5.0, 1.0, np.nan, 3.0],
        }
    )
    t = trends.trend(cells, "rate", "alpha", ["m"], +1)
    assert (t.pairs, t.along, t.against, t.flat) == (3, 1, 1, 1)
    assert t.mean_change == pytest.approx(0.0) and trends.verdict(t) == "no"
    t = trends.trend(cells, "time_all", "alpha", ["m"], -1, relative=True)
    assert (t.pairs, t.along, t.against, t.flat) == (2, 1, 0, 1)  # +2 % is unchanged
    assert trends.verdict(t) == "partly"
    assert trends.verdict(trends.Trend(3, 2, 0, 1, -1.0)) == "yes"
    assert trends.verdict(trends.Trend(3, 1, 1, 1, -1.0)) == "no"
    none = trends.trend(cells[cells.alpha == 1.0], "rate", "alpha", ["m"], +1)
    assert none.pairs == 0 and trends.verdict(none) == "cannot tell"
    with pytest.raises(ValueError, match="^sign"):
        trends.trend(cells, "rate", "alpha", ["m"], 0)
    with pytest.raises(ValueError, match="^frame: expected a column 'kappa'"):
        trends.trend(cells, "rate", "kappa", ["m"], 1)


def test_level_and_m_trends_pair_within_their_kind():
    cells = pd.DataFrame(
        {
            "kind": ["brightness"] * 2 + ["contrast"] * 3,
            "level": [1.0, 2.0, 5e-4, 5e-3, 1e-2],
            "kappa": 1.0,
            "alpha": 1.0,
            "time_all": [10.0, 20.0, 30.0, 5.0, 29.0],
            "paper_time_mean": [15.0, 40.0, 20.0, 25.0, 60.0],
        }
    )
    table = trends.trend_table(cells, ["kind", "level", "kappa", "alpha"], [])
    row = table.loc["Larger brightness / contrast changes cost more time"]
    assert row["the paper's numbers"] == "yes: 2 of 2 (+32.5 s)"
    assert row["ours"] == "partly: 1 of 2, 1 unchanged (+4.5 s)"  # 30 → 29 s: within 5 %
    assert list(table.index) == ["Larger brightness / contrast changes cost more time"]


def test_report_shows_figure_compact_table_and_links(tmp_path):
    table = tables.t_local(local_records())
    out = _results(tmp_path, table)
    text = report.write_report(out).read_text()
    assert "![t_local](figures/t_local.png)" in text
    assert text.count("figures/t_local.png") == 1  # not drawn twice
    assert "[tables/t_local.csv](tables/t_local.csv)" in text
    assert "| model | method | instances | holds / violated / unknown |" in text
    # cnn, alloc (heatmap): 8 holds, 8 refutations; 50 % over 8 cells; 30 s proofs, 0.1 s
    # refutations; the paper's mean over the m = 2 cells.
    paper = np.mean([v[2] for k, v in tables.PAPER_T_LOCAL.items() if k[0] == 2])
    paper_s = np.mean([v[0] for k, v in tables.PAPER_T_LOCAL.items() if k[0] == 2])
    row = (
        f"| cnn | alloc (heatmap) | 16 | 8 / 8 / 0 | 8 | 50% | {paper:.0%} | "
        f"{100 * (0.5 - paper):+.0f} pp | 30 | 0.1 | {paper_s:.3g} |"
    )
    assert row in text
    assert "| cnn_patch | pb | 16 | 8 / 0 / 8 | 8 | 50% |" in text
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
    # The paper's m = 2 cells rise with α in all 4 pairs (overlap × κ), by 34 pp on average.
    assert rate["the paper's numbers"] == "yes: 4 of 4 (+34 pp)"
    # Ours: the 'heatmap' reading holds only at α = 1.5 (+100 pp); the 'paper' one always.
    assert rate["cnn alloc (heatmap)"] == "yes: 4 of 4 (+100 pp)"
    assert rate["cnn alloc (paper)"] == "no: 0 of 4, 4 unchanged (+0 pp)"
    cost = trends_["Overlapping hulls cost more time"]
    assert cost["cnn pb"] == "yes: 4 of 4 (+150 s)"  # 200 s against 50 s
    # Refutations at α = 1 (0.1 s), proofs at α = 1.5 (30 s): time rises, against the paper.
    assert trends_.loc["cnn alloc (heatmap)", "Time per instance falls with α"] == (
        "no: 0 of 4, 4 against (+29.9 s)"
    )
    text = report.write_report(_results(tmp_path, table)).read_text()
    assert "| the paper states | the paper's numbers | cnn alloc (heatmap) |" in text
    assert "| *Verified rate rises with α* | yes: 4 of 4 (+34 pp) | yes: 4 of 4 (+100 pp) |" in text


def test_t_prob_reading_says_whether_soundness_rises_with_kappa():
    prob = pd.DataFrame(
        {
            "tolerance_units": ["heatmap"] * 4 + ["paper"] * 4,
            "kappa": [1.0, 1.0, 2.0, 2.0] * 2,
            "alpha": [1.0, 2.0] * 4,
            "soundness": [0.9, 0.95, 0.85, 0.97, 0.9, 0.9, 0.95, 0.95],
            "completeness": [0.1, 0.2, 0.05, 0.1] * 2,
        }
    )
    trends_ = report.trend_readings("t_prob", tables.t_prob(prob)).T
    assert list(trends_.columns) == [
        "Soundness rises with κ",
        "Soundness falls with α",
        "Completeness falls with κ",
    ]
    column = trends_["Soundness rises with κ"]
    # The paper: 0.998978 → 1.0 at α = 1, 0.988339 → 0.999999 at α = 2.
    assert column["the paper's numbers"] == "yes: 2 of 2 (+0.63 pp)"
    assert column["ours, 'heatmap' reading"] == "no: 1 of 2, 1 against (-1.5 pp)"
    assert column["ours, 'paper' reading"] == "yes: 2 of 2 (+5 pp)"
    # The paper: soundness falls with α (0.998978 → 0.988339 at κ = 1, 1 → 0.999999 at 2).
    falls = trends_["Soundness falls with α"]
    assert falls["the paper's numbers"].startswith("yes: 2 of 2")
    assert falls["ours, 'heatmap' reading"] == "no: 0 of 2, 2 against (+8.5 pp)"
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
    assert "| – | alloc | 16 | 8 / 8 / 0 | 8 | 50% |" in text
    assert text.split("| – | alloc |")[1].split("\n")[0].endswith("| – | – | 62.2 |")
    assert "| *Verified rate rises with α* | yes: 4 of 4 (+34 pp) | yes: 4 of 4 (+100 pp) |" in text
    # With a figure drawn from the old table: proof times absent, all-instance times shown.
    fig = comparison.plot_comparison(pd.read_csv(out / "tables" / "t_local.csv"), "old")
    assert fig.axes


def test_missing_tables_are_listed(tmp_path):
    text = report.write_report(tmp_path / "empty").read_text()
    for name in ("t_local", "t_global", "t_resnet", "t_prob", "f_sym"):
        assert f"*Table `{name}` is missing (its notebook has not run).*" in text
