"""kpstudy.study.tables on campaign records, as stored and as read back from CSV."""

import io

import numpy as np
import pandas as pd

from kpstudy.study import tables


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
