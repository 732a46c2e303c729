"""kpstudy.study.table_runs: one verification table from its campaigns, files and figures."""

import pytest

from kpstudy.study.table_runs import TABLES, run_table


def test_a_table_runs_its_campaigns_and_writes_its_files(study, tmp_path):
    data, checkpoint = study
    options = dict(
        grid_options=dict(alphas=[1.5], kappas=[1.0], ms=[2], overlapping=[True]),
        tolerance_units=("heatmap", "paper"),
        pose_bound={"tiny": dict(pose_bound_timeout=60.0, pose_bound_nodes=1)},
        timeout=30,
        nodes=2,
        check_samples=0,
    )
    result = run_table("t_resnet", {"tiny": str(checkpoint)}, data, tmp_path, **options)
    assert set(result.records.kind) == set(TABLES["t_resnet"].kinds)
    assert len(result.records) == 2 * 2  # two seed images, two readings
    assert set(result.table.tolerance_units) == {"heatmap", "paper"}
    for stem in ("t_resnet_records.csv", "t_resnet.csv", "t_resnet.md"):
        assert (tmp_path / "tables" / stem).stat().st_size > 0
    assert sorted(result.figures) == ["comparison", "pose_bound"]
    for path in result.figures.values():
        assert path.parent == tmp_path / "figures" and path.read_bytes()[:4] == b"\x89PNG"
    assert all(line.startswith("tiny: ") for line in result.readings)
    # A rerun resumes from the stores: the same records.
    again = run_table("t_resnet", {"tiny": str(checkpoint)}, data, tmp_path, **options)
    assert again.records["status"].tolist() == result.records["status"].tolist()


def test_an_unknown_table_is_refused_before_any_work(tmp_path):
    with pytest.raises(
        ValueError, match=r"^name: expected one of t_global, t_local, .*, got 't_prob'$"
    ):
        run_table("t_prob", {}, tmp_path, tmp_path, grid_options={})
    assert not any(tmp_path.iterdir())
