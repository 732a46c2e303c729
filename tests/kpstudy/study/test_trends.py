"""kpstudy.study.trends: the 95 % intervals of rates against hand-computed Wilson intervals,
and the verdicts on trends (shown / not shown / contradicted) on constructed tables."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from kpstudy.study import trends
from tests.helpers.records import wilson


@pytest.mark.parametrize(
    ("k", "n", "low", "high"),
    [
        (0, 10, 0.0, 0.2775328),  # z² / (n + z²)
        (10, 10, 0.7224672, 1.0),  # n / (n + z²)
        (3, 7, 0.1582199, 0.7495416),
        (8, 16, 0.2799957, 0.7200043),
        (1, 1, 0.2065493, 1.0),
    ],
)
def test_rate_interval_is_wilsons(k, n, low, high):
    assert trends.rate_interval(k, n) == pytest.approx((low, high), abs=1e-6)
    assert trends.rate_interval(k, n) == pytest.approx(wilson(k, n), abs=1e-9)
    assert trends.rate_interval(float(k), float(n)) == trends.rate_interval(k, n)  # from CSV


def test_rate_interval_level_and_edges():
    # 90 %: z = 1.644854, 0/10 → z² / (10 + z²) = 0.212942.
    assert trends.rate_interval(0, 10, level=0.90) == pytest.approx((0.0, 0.2129420), abs=1e-6)
    assert all(np.isnan(trends.rate_interval(0, 0)))
    assert all(np.isnan(trends.rate_interval(np.nan, 5)))
    for k, n in ((3, 2), (-1, 4), (1.5, 4)):
        with pytest.raises(ValueError, match="^k, n: expected integers"):
            trends.rate_interval(k, n)
    with pytest.raises(ValueError, match="^level"):
        trends.rate_interval(1, 2, level=95)


def test_rate_intervals_per_element_and_the_papers_200_seeds():
    low, high = trends.rate_intervals([0.0, 3 / 7, np.nan, 0.5], [10, 7, 5, 0])
    np.testing.assert_allclose(low[:2], [0.0, 0.1582199], atol=1e-6)
    np.testing.assert_allclose(high[:2], [0.2775328, 0.7495416], atol=1e-6)
    assert np.isnan(low[2:]).all() and np.isnan(high[2:]).all()
    # The paper's 55 % of 200 seeds: 110 / 200.
    low, high = trends.paper_interval([0.550, 0.169])
    assert (low[0], high[0]) == pytest.approx(wilson(110, 200), abs=1e-9)
    assert (low[0], high[0]) == pytest.approx((0.480756, 0.617359), abs=1e-6)
    assert (low[1], high[1]) == pytest.approx(wilson(34, 200), abs=1e-9)  # 33.8 → 34


def _rates(lo, hi, n=50):
    """Two pairs (m = 2, 3) of cells at α = 1 and α = 1.5, ``n`` seeds each: rates
    ``lo`` at α = 1 and ``hi`` at α = 1.5 (per pair)."""
    return pd.DataFrame(
        {
            "m": [2, 2, 3, 3],
            "alpha": [1.0, 1.5, 1.0, 1.5],
            "rate": [lo[0], hi[0], lo[1], hi[1]],
            "seeds_inside": n,
        }
    )


def test_rate_trend_verdicts_on_constructed_tables():
    args = ("rate", "alpha", ["m"], +1)
    shown = trends.trend(_rates((0.2, 0.3), (0.8, 0.7)), *args, count="seeds_inside")
    # Pooled: 25 of 100 at α = 1 against 75 of 100 at α = 1.5.
    assert shown.difference == pytest.approx(0.5)
    assert shown.p_value == pytest.approx(stats.fisher_exact([[75, 25], [25, 75]]).pvalue)
    assert trends.verdict(shown) == "shown" and shown.smallest == 50
    contra = trends.trend(_rates((0.8, 0.7), (0.2, 0.3)), *args, count="seeds_inside")
    assert contra.difference == pytest.approx(-0.5) and trends.verdict(contra) == "contradicted"
    # 25 + 26 of 100 against 27 + 26: +2 pp, far from significant; one pair moves against.
    flat = trends.trend(_rates((0.5, 0.52), (0.54, 0.52)), *args, count="seeds_inside")
    assert (flat.along, flat.against, flat.flat) == (1, 0, 1)
    assert flat.p_value > 0.5 and trends.verdict(flat) == "not shown"
    # The same numbers over 3 seeds a cell: nothing to see, and a smoke test.
    few = trends.trend(_rates((0.0, 0.0), (1.0, 1.0), n=3), *args, count="seeds_inside")
    assert few.smallest == 3 and few.p_value == pytest.approx(
        stats.fisher_exact([[6, 0], [0, 6]]).pvalue
    )
    assert trends.verdict(few) == "shown"  # 0/6 against 6/6: p = 0.002
    assert "smoke test, 3 per cell" in trends.describe(few)
    assert "smoke test" not in trends.describe(shown)
    # The paper's numbers: one count for every cell.
    paper = trends.trend(_rates((0.2, 0.3), (0.8, 0.7)), *args, count=200)
    assert paper.smallest == 200 and paper.p_value < shown.p_value
    # No count: counted, not tested.
    counted = trends.trend(_rates((0.2, 0.3), (0.8, 0.7)), *args)
    assert np.isnan(counted.p_value) and trends.verdict(counted) == "cannot tell"
    assert trends.describe(counted) == "cannot tell (no counts to test): 2 of 2 (+50 pp)"


def test_the_verdict_turns_at_the_level():
    def t(difference, p):
        return trends.Trend(2, 1, 0, 1, difference, difference, p, 50.0, sign=-1)

    assert trends.verdict(t(-0.1, 0.049)) == "shown"  # falls, as stated (sign −1)
    assert trends.verdict(t(-0.1, 0.051)) == "not shown"
    assert trends.verdict(t(+0.1, 0.049)) == "contradicted"
    assert trends.verdict(t(+0.1, 0.049), level=0.99) == "not shown"
    assert trends.verdict(trends.Trend(0, 0, 0, 0, np.nan)) == "cannot tell"
    assert trends.describe(t(-0.1, 0.0004), "time") == (
        "shown (p < 0.001): 1 of 2, 1 unchanged (-0.1 s)"
    )
    assert trends.describe(t(-0.1, 0.0123), "time").startswith("shown (p = 0.012):")


def test_time_trend_is_welchs_test_on_the_pooled_instances():
    """Per-cell mean, population std and count, as the tables store them, give the same
    test as Welch's on the raw union of the instances at each end."""
    rng = np.random.default_rng(0)
    raw = {
        (m, alpha): rng.exponential(scale, size)
        for (m, alpha), (scale, size) in {
            (2, 1.0): (20.0, 25),
            (2, 1.5): (8.0, 30),
            (3, 1.0): (40.0, 22),
            (3, 1.5): (15.0, 27),
        }.items()
    }
    cells = pd.DataFrame(
        [
            dict(m=m, alpha=a, time_all=v.mean(), time_std=v.std(ddof=0), timed=len(v))
            for (m, a), v in raw.items()
        ]
    )
    t = trends.trend(cells, "time_all", "alpha", ["m"], -1, True, count="timed", spread="time_std")
    lo = np.concatenate([raw[2, 1.0], raw[3, 1.0]])
    hi = np.concatenate([raw[2, 1.5], raw[3, 1.5]])
    welch = stats.ttest_ind(hi, lo, equal_var=False)
    assert t.p_value == pytest.approx(welch.pvalue, rel=1e-9)
    assert t.difference == pytest.approx(hi.mean() - lo.mean())
    assert welch.pvalue < 0.01 and trends.verdict(t) == "shown"
    # Against the statement: the same cells read as "time rises with α".
    rises = trends.trend(
        cells, "time_all", "alpha", ["m"], +1, True, count="timed", spread="time_std"
    )
    assert trends.verdict(rises) == "contradicted"
    # The paper's standard deviations are sample ones (ddof = 1): the same test.
    paper = cells.assign(time_std=[np.std(v, ddof=1) for v in raw.values()])
    t1 = trends.trend(paper, "time_all", "alpha", ["m"], -1, True, "timed", "time_std", ddof=1)
    assert t1.p_value == pytest.approx(welch.pvalue, rel=1e-9)
    # Read with the wrong ddof, the p-value moves: the test depends on it.
    t0 = trends.trend(paper, "time_all", "alpha", ["m"], -1, True, "timed", "time_std", ddof=0)
    assert t0.p_value != pytest.approx(welch.pvalue, rel=1e-6)


def test_time_verdicts_on_constructed_tables():
    def cells(lo_mean, hi_mean, std, n=200):
        return pd.DataFrame(
            {
                "overlapping": [False, True, False, True],
                "kappa": [1.0, 1.0, 1.5, 1.5],
                "time_all": [lo_mean, hi_mean, lo_mean, hi_mean],
                "time_std": std,
                "timed": n,
            }
        )

    def judge(frame):
        t = trends.trend(
            frame, "time_all", "overlapping", ["kappa"], +1, True, "timed", "time_std", 1
        )
        return trends.verdict(t), t

    assert judge(cells(50.0, 80.0, 100.0))[0] == "shown"  # t = 30 / (100 √(2/400)) ≈ 4.2
    assert judge(cells(80.0, 50.0, 100.0))[0] == "contradicted"
    verdict, t = judge(cells(50.0, 55.0, 100.0))  # t ≈ 0.7
    assert verdict == "not shown" and (t.along, t.pairs) == (2, 2)
    verdict, t = judge(cells(50.0, 80.0, 100.0, n=5))  # too few instances to tell
    assert verdict == "not shown" and t.smallest == 5
    assert "smoke test, 5 per cell" in trends.describe(t, "time")


def test_trend_table_tests_the_paper_and_each_series():
    cells = pd.concat(
        [
            _rates((0.2, 0.3), (0.8, 0.7), n=40).assign(method="a"),
            _rates((0.8, 0.7), (0.2, 0.3), n=40).assign(method="b"),
            _rates((0.5, 0.5), (0.5, 0.5), n=2).assign(method="c"),
        ],
        ignore_index=True,
    ).assign(paper_rate=lambda f: np.where(f.alpha == 1.0, 0.55, 0.885))
    table = trends.trend_table(cells, ["m", "alpha"], ["method"])
    row = table.loc["Verified rate rises with α"]
    assert row["the paper's numbers"].startswith("shown (p < 0.001): 2 of 2 (+34 pp)")
    assert row["a"].startswith("shown (p < 0.001)")
    assert row["b"].startswith("contradicted (p < 0.001)")
    assert row["c"] == "not shown (p = 1; smoke test, 2 per cell): 0 of 2, 2 unchanged (+0 pp)"
    no_counts = trends.trend_table(cells.drop(columns="seeds_inside"), ["m", "alpha"], ["method"])
    assert no_counts.loc["Verified rate rises with α", "a"].startswith("cannot tell")


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
    assert t.mean_change == pytest.approx(0.0)
    assert trends.verdict(t) == "cannot tell"  # no seed counts: nothing to test
    t = trends.trend(cells, "time_all", "alpha", ["m"], -1, relative=True)
    assert (t.pairs, t.along, t.against, t.flat) == (2, 1, 0, 1)  # +2 % is unchanged
    # With 10 seeds a cell: pooled 9 of 30 at α = 1 (2 + 4 + 3) against 9 of 30 at α = 1.5.
    t = trends.trend(cells.assign(n=10), "rate", "alpha", ["m"], +1, count="n")
    assert t.difference == 0 and t.p_value == pytest.approx(1.0)
    assert trends.verdict(t) == "not shown"
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
            "time_std": [5.0, 5.0, 10.0, 1.0, 10.0],
            "timed": 30,
            "paper_time_mean": [15.0, 40.0, 20.0, 25.0, 60.0],
            "paper_time_std": [30.0, 60.0, 30.0, 40.0, 90.0],
        }
    )
    table = trends.trend_table(cells, ["kind", "level", "kappa", "alpha"], [])
    row = table.loc["Larger brightness / contrast changes cost more time"]
    assert row["the paper's numbers"] == "shown (p < 0.001): 2 of 2 (+32.5 s)"
    # Pooled: 20 s (10 and 30) at the smallest levels against 24.5 s (20 and 29) at the
    # largest, 60 instances each; 30 → 29 s alone is within 5 %.
    assert row["ours"] == "shown (p = 0.029): 1 of 2, 1 unchanged (+4.5 s)"
    spread = trends.trend_table(
        cells.assign(time_std=[5.0, 5.0, 30.0, 1.0, 30.0]), ["kind", "level", "kappa", "alpha"], []
    )
    assert spread.iloc[0]["ours"] == "not shown (p = 0.29): 1 of 2, 1 unchanged (+4.5 s)"
    assert list(table.index) == ["Larger brightness / contrast changes cost more time"]
