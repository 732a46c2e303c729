"""benchmarks/hull_decisions.py: its summary of campaign records and its refusal of a
results folder without data or models (the campaigns themselves are the study's, tested
in tests/kpstudy/study)."""

import pandas as pd
import pytest

from benchmarks import hull_decisions


def test_the_summary_counts_verdicts_and_decisions_within_each_limit():
    records = pd.DataFrame(
        {
            "pb_status": ["holds", "violated", "unknown", "holds"],
            "pb_time": [12.0, 0.5, 600.0, 90.0],
        }
    )
    out = hull_decisions.summarise(records, [60.0, 600.0])
    assert out == {
        "records": 4,
        "holds": 2,
        "violated": 1,
        "unknown": 1,
        "decided_within_60s": 0.5,
        "decided_within_600s": 0.75,
        "median_seconds": 51.0,
        "max_seconds": 600.0,
    }


def test_a_results_folder_without_its_models_is_one_line(tmp_path, capsys):
    (tmp_path / "data").mkdir()
    with pytest.raises(SystemExit) as ended:
        hull_decisions.main(["--results", str(tmp_path), "--models", "cnn"])
    assert ended.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == f"hull_decisions: error: results: missing {tmp_path / 'models' / 'cnn.pt'}"
