"""kpstudy.study.tables on campaign records, as stored and as read back from CSV: every
summary column against counts made by hand on small record frames, and the pose-bound
method's columns (which rule decided, what a time cap ended)."""

import io
import math

import numpy as np
import pandas as pd
import pytest

from kpstudy.study import tables


def _record(status, inside, **fields):
    """One campaign record: of the contrast family at level 5e-4, κ = 1, α = 1 unless
    ``fields`` say otherwise."""
    grid = dict(kind="contrast", level=5e-4, image_id=0, kappa=1.0, alpha=1.0)
    return {**grid, "status": status, "seed_inside": inside, **fields}


def _cells():
    """Two cells (α = 1, α = 2). Ξ at α = 1 is [10°, 10°, 10°, 4, 4, 20 m]."""
    near = [1.0] * 6  # inside Ξ at α = 1
    tx5 = [0.0, 0.0, 0.0, 5.0, 0.0, 0.0]  # outside Ξ at α = 1 (tx > 4), inside at α = 2
    a1 = [
        # status, inside, λ of the counterexample, dv, time, pb_status, pb_rule, pb_nonlinear
        ("holds", True, None, [[1, 0], [2, 2]], 1.0, "holds", "enumeration", near),
        ("violated", True, [0.0, 0.0], [[0, 0], [0, 0]], 3.0, "violated", "witness", None),
        ("violated", False, [0.5, 0.0], [[1, 1], [1, 1]], 2.0, "holds", "linearised", tx5),
        ("unknown", True, None, [[3, 0], [0, 0]], 6.0, "holds", "linearised", near),
        ("holds", False, None, [[0, 1], [0, 0]], 0.0, "unknown", None, near),
    ]
    a2 = [
        ("violated", False, [0.0, 0.0], [[2, 2], [2, 2]], 1.0, "violated", "witness", None),
        ("holds", True, None, [[2, 2], [2, 2]], 2.0, "unknown", "enumeration", near),
        ("holds", True, None, [[2, 2], [2, 2]], 6.0, "holds", "linearised", tx5),
    ]
    # Whether the seed's argmax → PnP pose lies in Ξ (None: a record from before the field,
    # which counts the target model's `inside`): α = 1 rows 0, 2, 3 (by `inside`), 4.
    argmax_inside = {1.0: [True, False, True, None, True], 2.0: [None] * 3}
    rows = []
    for alpha, cell in ((1.0, a1), (2.0, a2)):
        for i, (status, inside, lam, dv, t, pb, rule, nonlinear) in enumerate(cell):
            rows.append(
                _record(
                    status,
                    inside,
                    alpha=alpha,
                    image_id=i,
                    counterexample=lam,
                    dv=dv,
                    time=t,
                    pb_status=pb,
                    pb_seed_inside=argmax_inside[alpha][i],
                    pb_rule=rule,
                    pb_time=10.0 * (i + 1),
                    pb_nonlinear=nonlinear,
                    argmax_outside=0.01 * i**2,
                )
            )
    # An instance that could not be certified: it counts in `instances` only.
    rows.append(dict(kind="contrast", level=5e-4, image_id=9, kappa=1.0, alpha=1.0, status="error"))
    return pd.DataFrame(rows)


def _both(records):
    """The records as stored and as read back from their CSV."""
    return records, pd.read_csv(io.StringIO(records.to_csv(index=False)))


@pytest.fixture(params=["stored", "csv"])
def cells(request):
    """The summary rows of :func:`_cells` at α = 1 and α = 2."""
    table = tables.summarise(_both(_cells())[request.param == "csv"], ["alpha"])
    return table.set_index("alpha").loc[1.0], table.set_index("alpha").loc[2.0]


def test_counts_rates_and_times_per_cell(cells):
    one, two = cells
    # α = 1: 5 certified + 1 error; seeds inside: rows 0, 1, 3.
    assert (one.instances, one.seeds_inside, one.errors) == (6, 3, 1)
    assert (one.holds, one.violated, one.unknown) == (2, 2, 1)
    assert one.violated_at_seed == 1  # row 1 (λ = 0); row 2's λ is not the seed
    assert one.verified_rate == pytest.approx(1 / 3)  # row 0; row 4 holds outside Ξ
    # Wilson at 95 % for 1 of 3, by hand: (k + z²/2 ± z √(k(n−k)/n + z²/4)) / (n + z²).
    assert (one.verified_rate_lo, one.verified_rate_hi) == pytest.approx(
        (0.0614919, 0.7923404), abs=1e-6
    )
    assert one.decided == pytest.approx(4 / 5)  # all but row 3
    assert one.dv_mean == pytest.approx(13 / 20) and one.dv_zero == pytest.approx(11 / 20)
    assert one.time_mean == pytest.approx(12 / 5)  # 1 + 3 + 2 + 6 + 0, the error left out
    assert one.time_std == pytest.approx(math.sqrt(21.2 / 5))  # population std
    # 0, 1, 2, 3, 6 s: median 2, quartiles 1 and 3.
    assert (one.time_median, one.time_q1, one.time_q3) == (2.0, 1.0, 3.0)
    assert one.not_certifiable == 0
    assert (one.time_holds_mean, one.time_violated_mean, one.time_unknown_mean) == (0.5, 2.5, 6)
    assert one.argmax_outside == pytest.approx(0.08)  # over 'holds': rows 0 (0), 4 (0.16)
    # α = 2: no error; the violated seed's λ read back from CSV text is still λ = 0.
    assert (two.instances, two.seeds_inside, two.errors) == (3, 2, 0)
    assert (two.holds, two.violated, two.unknown, two.violated_at_seed) == (2, 1, 0, 1)
    assert two.verified_rate == 1.0 and two.decided == 1.0
    assert (two.verified_rate_lo, two.verified_rate_hi) == pytest.approx((0.3423802, 1.0), abs=1e-6)
    # 1, 2, 6 s: median 2, quartiles 1.5 and 4 (linear between the order statistics).
    assert (two.time_median, two.time_q1, two.time_q3) == (2.0, 1.5, 4.0)
    assert two.dv_mean == 2.0 and two.dv_zero == 0.0
    assert two.time_mean == 3.0 and two.time_std == pytest.approx(math.sqrt(14 / 3))
    assert (two.time_holds_mean, two.time_violated_mean) == (4.0, 1.0)
    assert np.isnan(two.time_unknown_mean)  # none


def test_pose_bound_columns_per_cell(cells):
    one, two = cells
    assert (one.pb_holds, one.pb_violated, one.pb_unknown) == (3, 1, 1)
    assert one.pb_decided == pytest.approx(4 / 5)  # all but row 4
    # Its own denominator: seeds whose argmax pose is inside (rows 0, 2, 3, 4), all but
    # row 4 proved; over the target model's (rows 0, 1, 3) it would be 2/3.
    assert one.pb_seeds_inside == 4 and one.pb_verified_rate == 0.75
    assert (one.pb_verified_rate_lo, one.pb_verified_rate_hi) == pytest.approx(
        (0.3006418, 0.9544127), abs=1e-6
    )  # 3 of 4
    assert one.pb_time_mean == 30.0  # 10 … 50
    assert one.pb_time_std == pytest.approx(math.sqrt(200.0))
    assert (one.pb_time_median, one.pb_time_q1, one.pb_time_q3) == (30.0, 20.0, 40.0)
    assert one.pb_time_holds_mean == pytest.approx(80 / 3)  # rows 0, 2, 3
    assert (one.pb_time_violated_mean, one.pb_time_unknown_mean) == (20.0, 50.0)
    # Row 4 has no pb_rule: an 'unknown' from before the field was decided by 'linearised'.
    assert (one.pb_by_witness, one.pb_by_enumeration, one.pb_by_linearised) == (1, 1, 3)
    assert one.pb_enumeration_holds == 1
    assert one.pb_nonlinear_outside == 1  # row 2: tx = 5 > 4
    assert (one.pb_only, one.allocation_only) == (1, 0)  # row 3; row 4 is outside Ξ
    assert (two.pb_holds, two.pb_violated, two.pb_unknown) == (1, 1, 1)
    assert two.pb_decided == pytest.approx(2 / 3)
    assert two.pb_seeds_inside == 2 and two.pb_verified_rate == 0.5  # the target model's
    assert two.pb_time_mean == 20.0
    assert (two.pb_time_holds_mean, two.pb_time_violated_mean, two.pb_time_unknown_mean) == (
        30.0,
        10.0,
        20.0,
    )
    assert (two.pb_by_enumeration, two.pb_enumeration_holds) == (1, 0)  # row 1: unknown
    assert two.pb_nonlinear_outside == 0  # tx = 5 is inside Ξ at α = 2 (8)
    assert (two.pb_only, two.allocation_only) == (0, 1)  # row 1: holds, pose bound unknown


def test_a_cell_without_a_seed_inside_has_no_rate():
    records = pd.DataFrame(
        [
            _record("holds", False, time=1.0, pb_status="holds", pb_time=1.0, pb_nonlinear=[0] * 6),
            _record("violated", False, time=1.0, pb_status=None, pb_time=None, pb_nonlinear=None),
        ]
    )
    row = tables.summarise(records, ["alpha"]).iloc[0]
    assert row.seeds_inside == 0 and np.isnan(row.verified_rate)
    assert np.isnan(row.pb_verified_rate) and row.pb_holds == 1 and row.pb_unknown == 0
    assert row.pb_time_mean == 1.0  # over the records with a pose bound
    with pytest.raises(ValueError, match=r"records: .*\['seed_inside'\]"):
        tables.summarise(records.drop(columns="seed_inside"), ["alpha"])


@pytest.mark.parametrize("form", ["stored", "csv"])
def test_not_certifiable_has_its_own_column_and_stays_in_the_rate(form):
    """A seed whose pixel grid alone exceeds ε / κ: counted apart, never decided, in the
    verified rate's denominator when inside Ξ; its cells (none) are left out of the δv
    columns, which read float half-widths as well as integers."""
    rows = [
        _record("holds", True, image_id=0, time=2.0, dv=[[0.5, 1.0], [1.5, 0.0]]),
        _record("not_certifiable", True, image_id=1, time=0.0, dv=None),
        _record("not_certifiable", False, image_id=2, time=0.0, dv=[[0, 0], [0, 0]]),
        _record(
            "violated", True, image_id=3, time=1.0, dv=[[1, 1], [1, 1]], counterexample=[0.0, 0.0]
        ),  # fmt: skip
        dict(kind="contrast", level=5e-4, image_id=4, kappa=1.0, alpha=1.0, status="error"),
    ]
    records = _both(pd.DataFrame(rows))[form == "csv"]
    row = tables.t_global(records).iloc[0]
    assert (row.instances, row.errors) == (5, 1)
    assert (row.holds, row.violated, row.unknown, row.not_certifiable) == (1, 1, 0, 2)
    assert row.holds + row.violated + row.unknown + row.not_certifiable + row.errors == 5
    assert row.seeds_inside == 3 and row.verified_rate == pytest.approx(1 / 3)
    assert row.decided == pytest.approx(2 / 4)  # holds and violated of the 4 that ran
    # δv over seeds 0 and 3 only: 0.5, 1, 1.5, 0, 1, 1, 1, 1.
    assert row.dv_mean == pytest.approx(7 / 8) and row.dv_zero == pytest.approx(1 / 8)
    assert row.time_mean == pytest.approx(0.75)  # 2, 0, 0, 1
    # The paper's 57 % of 200 seeds: 114 of 200.
    assert (row.paper_rate, row.paper_rate_lo) == (0.570, pytest.approx(0.500705, abs=1e-6))
    only = _both(pd.DataFrame(rows[1:3]))[form == "csv"]
    row = tables.t_global(only).iloc[0]
    assert row.not_certifiable == 2 and row.verified_rate == 0.0
    assert np.isnan(row.dv_mean) and np.isnan(row.dv_zero)  # no cell to measure
    assert (row.verified_rate_lo, row.verified_rate_hi) == pytest.approx(
        (0.0, 0.7934506), abs=1e-6
    )  # 0 of 1: z² / (1 + z²)


def test_t_global_has_a_row_per_model_reading_and_cell_with_the_papers_numbers():
    rows = []
    for model in ("cnn", "cnn_patch"):
        for units, kappa, status in ((None, 1.0, "holds"), ("heatmap", 1.0, "violated")):
            rows.append(_record(status, True, model=model, tolerance_units=units, kappa=kappa))
        rows.append(_record("holds", True, model=model, tolerance_units="paper", kappa=1.5))
        rows.append(
            _record("holds", True, model=model, kind="brightness", level=2.0, tolerance_units=None)
        )
    rows.append(_record("holds", True, model="cnn", kind="objects", m=2, overlapping=False))
    records = pd.DataFrame(rows).assign(time=1.0, clipped_fraction=0.1 * np.arange(len(rows)))
    # A stored level only near the paper's (float text) finds the paper's cell.
    records.loc[records.kind == "contrast", "level"] = 5e-4 * (1 + 1e-9)
    table = tables.t_global(records)
    keys = list(zip(table.model, table.tolerance_units, table.kind, table.kappa))
    assert keys == [  # sorted; the record before the reading field counts as 'heatmap'
        ("cnn", "heatmap", "brightness", 1.0),
        ("cnn", "heatmap", "contrast", 1.0),
        ("cnn", "paper", "contrast", 1.5),
        ("cnn_patch", "heatmap", "brightness", 1.0),
        ("cnn_patch", "heatmap", "contrast", 1.0),
        ("cnn_patch", "paper", "contrast", 1.5),
    ]
    assert list(table.instances) == [1, 2, 1, 1, 2, 1]  # the objects record is not global
    assert list(table.holds) == [1, 1, 1, 1, 1, 1] and list(table.verified_rate[1:3]) == [0.5, 1]
    assert list(table.paper_rate[:3]) == [0.560, 0.570, 0.173]  # (kind, level, κ, α = 1)
    assert list(table.paper_time_mean[:3]) == [223.4, 79.7, 133.9]
    assert list(table.paper_time_std[:3]) == [301.9, 105.5, 95.5]
    # Mean over the cell's records (0.1 × their row): cnn's are rows 0–3, cnn_patch's 4–7.
    np.testing.assert_allclose(table.clipped_fraction, [0.3, 0.05, 0.2, 0.7, 0.45, 0.6])


def test_t_local_and_t_resnet_take_their_kinds_and_paper_cells():
    rows = [
        _record("holds", True, kind="objects", m=2, overlapping=False),
        _record("unknown", True, kind="objects", m=2, overlapping=False),
        _record("holds", True, kind="objects", m=5, overlapping=True),  # no paper cell
        _record("holds", True, kind="blocks", overlapping=True, alpha=1.5),
        _record("violated", True, kind="blocks", overlapping=False, alpha=1.5),
        _record("holds", True, kind="blocks", overlapping=False, alpha=1.5),
        _record("holds", True),  # contrast: in neither
    ]
    records = pd.DataFrame(rows).assign(time=2.0)
    local = tables.t_local(records)
    assert list(zip(local.m, local.overlapping)) == [(2, False), (5, True)]
    assert list(local.instances) == [2, 1] and list(local.verified_rate) == [0.5, 1.0]
    assert (local.paper_rate[0], local.paper_time_mean[0], local.paper_time_std[0]) == (
        0.550,
        38.3,
        56.7,
    )
    assert local.paper_rate.isna().tolist() == [False, True]
    resnet = tables.t_resnet(records)
    assert list(resnet.overlapping) == [False, True] and list(resnet.instances) == [2, 1]
    assert list(resnet.verified_rate) == [0.5, 1.0] and list(resnet.time_mean) == [2.0, 2.0]
    assert list(resnet.paper_rate) == [0.935, 0.940]
    assert list(resnet.paper_time_mean) == [314.4, 1571.7]
    with pytest.raises(ValueError, match="'kind'"):
        tables.t_local(records.drop(columns="kind"))


def test_t_prob_puts_the_papers_soundness_and_completeness_beside_ours():
    ours = pd.DataFrame(dict(kappa=[1.0, 2.0, 3.0], alpha=[1.0, 0.5, 1.0], soundness=[1, 1, 1]))
    out = tables.t_prob(ours)
    assert list(out.paper_soundness[:2]) == [0.998978, 1.0] and np.isnan(out.paper_soundness[2])
    assert list(out.paper_completeness[:2]) == [3.07e-5, 0.0]
    assert list(out.soundness) == [1, 1, 1] and "paper_soundness" not in ours


@pytest.mark.parametrize("form", ["stored", "csv"])
def test_pose_bound_ratios_one_row_per_hull(form):
    """The bound depends on the hull only: one row per hull whatever its α and κ, divided
    by Ξ at α = 1; a record without a bound (its seed refuted it) is left out."""
    bound = [5.0, 10.0, 20.0, 2.0, 4.0, 10.0]
    rows = [
        _record("holds", True, image_id=0, alpha=1.0, pb_bound=bound),
        _record("holds", True, image_id=0, alpha=2.0, pb_bound=bound),
        _record("holds", True, image_id=0, kind="brightness", level=2.0, pb_bound=[1.0] * 6),
        _record("violated", True, image_id=1, pb_bound=None),
    ]
    records = _both(pd.DataFrame(rows))[form == "csv"]
    ratios = tables.pose_bound_ratios(records)
    assert list(ratios.columns) == ["kind", "image_id", "level", *tables.POSE_AXES]
    assert list(ratios.kind) == ["contrast", "brightness"]
    np.testing.assert_allclose(ratios.loc[0, list(tables.POSE_AXES)], [0.5, 1, 2, 0.5, 1, 0.5])
    np.testing.assert_allclose(
        ratios.loc[1, list(tables.POSE_AXES)], [0.1, 0.1, 0.1, 0.25, 0.25, 0.05]
    )
    assert tables.pose_bound_ratios(records, "pb_exact").empty  # none enumerated
    with pytest.raises(ValueError, match="^column"):
        tables.pose_bound_ratios(records, "pb_nonlinear")


def _records():
    rows = []
    for image_id, (status, pb, lam, nonlinear) in enumerate(
        [
            ("violated", "holds", [0.0, 0.0], [1.0] * 6),  # pose bound only, nonlinear inside
            ("violated", "holds", [0.2, 0.1], [20.0] * 6),  # nonlinear corner leaves Ξ
            ("holds", "holds", None, [1.0] * 6),
            ("violated", "unknown", [0.0, 0.0], [50.0] * 6),
        ]
    ):
        rows.append(
            dict(
                kind="contrast",
                level=5e-4,
                image_id=image_id,
                alpha=1.0,
                kappa=1.0,
                status=status,
                time=0.1,
                seed_inside=True,
                counterexample=lam,
                dv=[[1, 0]] * 23,
                pb_status=pb,
                pb_time=2.0,
                pb_bound=[0.5 * image_id + 1.0] * 6,
                pb_nonlinear=nonlinear,
            )
        )
    return pd.DataFrame(rows)


def test_pose_bound_columns_from_stored_and_csv_records():
    stored = _records()
    from_csv = pd.read_csv(io.StringIO(stored.to_csv(index=False)))
    for records in (stored, from_csv):
        row = tables.t_global(records).iloc[0]
        assert (row.holds, row.violated, row.violated_at_seed) == (1, 3, 2)
        assert row.pb_holds == 3 and row.pb_verified_rate == 0.75
        assert (row.pb_only, row.allocation_only, row.pb_nonlinear_outside) == (2, 0, 1)
        ratios = tables.pose_bound_ratios(records)
        assert len(ratios) == 4
        np.testing.assert_allclose(ratios.tz, (0.5 * np.arange(4) + 1.0) / 20.0)


def test_readings_get_a_row_each_and_a_sentence_naming_the_nearer():
    heatmap = _records()  # from before the field: the 'heatmap' reading
    paper = _records().drop(columns=[c for c in _records() if c.startswith("pb_")])
    paper = paper.assign(
        tolerance_units="paper", status="holds", counterexample=None, argmax_outside=0.25
    )
    table = tables.t_global(pd.concat([heatmap, paper], ignore_index=True))
    by = table.set_index("tolerance_units")
    assert list(by.index) == ["heatmap", "paper"]
    assert by.loc["paper", "holds"] == 4 and by.loc["paper", "argmax_outside"] == 0.25
    assert np.isnan(by.loc["paper", "pb_holds"]) and by.loc["heatmap", "pb_holds"] == 3
    assert by.loc["heatmap", "verified_rate"] == 0.25 and by.loc["paper", "verified_rate"] == 1.0
    sentence = tables.reading_comparison(table, "verified_rate", "paper_rate", "Verified rate")
    # Paper cell (contrast 5e-4, κ = 1, α = 1): 0.570; |0.25 − 0.57| < |1.0 − 0.57|.
    assert sentence.startswith("Verified rate: under the 'heatmap' reading")
    assert "0.32" in sentence and "under the 'paper' reading by 0.43" in sentence
    assert (
        tables.reading_comparison(tables.t_global(heatmap), "verified_rate", "paper_rate", "x")
        is None
    )


def test_instance_label_names_records_as_stored_and_read_back_from_csv():
    records = pd.DataFrame(
        [
            dict(model="cnn", tolerance_units="paper", kind="objects", image_id=12,
                 m=3, overlapping=True, level=None, kappa=1.5, alpha=1.0),
            dict(model="cnn", tolerance_units="paper", kind="brightness", image_id=7,
                 m=None, overlapping=None, level=2.0, kappa=1.0, alpha=0.5),
            dict(model="cnn", tolerance_units="paper", kind="objects", image_id=123456789,
                 m=2, overlapping=False, level=None, kappa=1.0, alpha=1.5),
        ]
    )  # fmt: skip
    expected = [
        "cnn paper objects image 12 α=1 κ=1.5 m=3 overlapping",
        "cnn paper brightness image 7 α=0.5 κ=1 level=2",
        "cnn paper objects image 123456789 α=1.5 κ=1 m=2 non-overlapping",
    ]
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        assert [tables.instance_label(r) for _, r in frame.iterrows()] == expected
    assert tables.instance_label({"overlapping": "False", "m": "2"}) == "m=2 non-overlapping"
    assert tables.instance_label({}) == ""


def _pose_bound_records():
    rows = []
    for image_id, (pb_status, rule, exact) in enumerate(
        [
            ("holds", "enumeration", [1.0] * 6),
            ("unknown", "enumeration", [1.0, 30.0, 1.0, 1.0, 1.0, 1.0]),
            ("violated", "witness", None),
            ("holds", "linearised", None),
            ("unknown", "enumeration", [np.inf] * 6),
        ]
    ):
        rows.append(
            dict(
                kind="brightness",
                level=1.0,
                image_id=image_id,
                alpha=1.0,
                kappa=1.0,
                status="violated",
                time=0.1,
                seed_inside=True,
                counterexample=[0.0],
                pb_status=pb_status,
                pb_rule=rule,
                pb_time=1.0,
                pb_bound=[2.0] * 6,
                pb_exact=exact,
                pb_nonlinear=[1.0] * 6,
            )
        )
    return pd.DataFrame(rows)


def test_tables_count_the_rules_and_label_the_linearised_bound():
    stored = _pose_bound_records()
    from_csv = pd.read_csv(io.StringIO(stored.to_csv(index=False)))
    for records in (stored, from_csv):
        row = tables.t_global(records).iloc[0]
        assert (row.pb_holds, row.pb_violated, row.pb_unknown) == (2, 1, 2)
        assert (row.pb_by_witness, row.pb_by_enumeration, row.pb_by_linearised) == (1, 3, 1)
        assert row.pb_enumeration_holds == 1
        exact = tables.pose_bound_ratios(records, "pb_exact")
        assert exact.image_id.tolist() == [0, 1, 4]
        np.testing.assert_allclose(exact.pitch, [0.1, 3.0, np.inf])
        fig = tables.plot_pose_bounds(records, "T-global")
        ax = fig.axes[0]
        labels = ax.get_legend_handles_labels()[1]
        assert "linearised bound" in labels and "certified" not in ax.get_ylabel()
        assert any(label.startswith("certified") for label in labels)
    # Records from before pb_rule: violated by a witness, the rest by the linearised bound.
    old = stored.drop(columns=["pb_rule", "pb_exact"])
    row = tables.t_global(old).iloc[0]
    assert (row.pb_by_witness, row.pb_by_enumeration, row.pb_by_linearised) == (1, 0, 4)
    assert tables.pose_bound_ratios(old, "pb_exact").empty
    labels = tables.plot_pose_bounds(old, "old").axes[0].get_legend_handles_labels()[1]
    assert "linearised bound" in labels and not any(s.startswith("certified") for s in labels)


def test_the_pose_bound_rate_counts_the_seeds_its_pipeline_gets_right():
    records = _pose_bound_records()  # 5 records, every seed inside Ξ for the target model
    row = tables.t_global(records).iloc[0]
    assert row.pb_seeds_inside == 5 and row.pb_verified_rate == pytest.approx(2 / 5)
    assert row.pb_decided == pytest.approx(3 / 5) and row.decided == 1.0
    # The argmax pipeline right at 3 seeds, both holds among them; the target model at 2.
    records["pb_seed_inside"] = [s == "holds" or i == 2 for i, s in enumerate(records.pb_status)]
    records["seed_inside"] = [True, False, False, True, False]
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        row = tables.t_global(frame).iloc[0]
        assert (row.pb_seeds_inside, row.seeds_inside) == (3, 2)
        assert row.pb_verified_rate == pytest.approx(2 / 3)  # records 0 and 3 of 0, 2, 3
    # A store mixing records with and without the field: the old ones count the target's.
    records["pb_seed_inside"] = records["pb_seed_inside"].astype(object)
    records.loc[[0, 2], "pb_seed_inside"] = None  # target: inside at 0, outside at 2
    row = tables.t_global(records).iloc[0]
    assert row.pb_seeds_inside == 2 and row.pb_verified_rate == 1.0  # records 0 and 3


def test_the_tables_count_the_searches_the_time_cap_ended():
    records = _pose_bound_records()
    records["stopped"] = ["time", "nodes", None, "stop", "time"]
    records["pb_stopped"] = ["nodes", "time", "witness", None, None]
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        row = tables.t_global(frame).iloc[0]
        assert (row.capped, row.pb_capped) == (2, 1)
    from kpstudy.study.report import campaign_summary

    line = campaign_summary(tables.t_global(records))[-1]
    assert "2 of the allocation method's and 1 of the pose-bound method's" in line
    # Records from before the fields: no column, no sentence.
    old = tables.t_global(records.drop(columns=["stopped", "pb_stopped"]))
    assert "capped" not in old and np.isnan(old.pb_capped.iloc[0])
    assert not any("time cap" in s for s in campaign_summary(old))


def test_the_pose_bound_decided_fraction_counts_its_own_records_only():
    records = _pose_bound_records()  # holds, unknown, violated, holds, unknown
    records["pb_status"] = records["pb_status"].astype(object)
    records.loc[4, "pb_status"] = None  # an instance the pose-bound method did not run
    row = tables.t_global(records).iloc[0]
    assert row.pb_decided == pytest.approx(3 / 4) and row.pb_unknown == 1


def test_decided_by_nodes_reads_each_search_at_each_node_count():
    records = pd.DataFrame(
        {
            "model": "cnn",
            "tolerance_units": ["heatmap"] * 5 + ["paper"] * 2,
            "status": ["violated", "holds", "unknown", "holds", "error", "holds", "unknown"],
            "nodes": [0, 5, 70, 64, None, 1, 2],
            "pb_status": ["holds", "holds", "violated", "unknown", None, None, None],
            "pb_nodes": [17, 300, 0, 768, None, None, None],
        }
    )
    shares = tables.decided_by_nodes(records).set_index(["tolerance_units", "method"])
    assert list(shares.index) == [("heatmap", "alloc"), ("heatmap", "pb"), ("paper", "alloc")]
    alloc = shares.loc[("heatmap", "alloc")]  # the error is no search: 4 instances
    assert alloc["instances"] == 4 and alloc["decided"] == 0.75
    assert [alloc[f"≤ {n}"] for n in (0, 1, 4, 16, 64)] == [0.25, 0.25, 0.25, 0.5, 0.75]
    assert alloc["≤ 256"] == 0.75 and np.isnan(alloc["≤ 1024"])  # 256 covers its 70 nodes
    assert "≤ 4096" not in shares.columns  # 1024 covers the most nodes any search used
    pb = shares.loc[("heatmap", "pb")]
    assert [pb[f"≤ {n}"] for n in (0, 16, 64, 256)] == [0.25, 0.25, 0.5, 0.5]
    assert pb["≤ 1024"] == pb["decided"] == 0.75
    paper = shares.loc[("paper", "alloc")]
    assert paper["instances"] == 2 and paper["≤ 0"] == 0 and paper["≤ 1"] == 0.5
    assert tables.decided_by_nodes(records.drop(columns=["nodes", "pb_nodes"])).empty
