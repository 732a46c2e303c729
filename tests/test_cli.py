import subprocess
import sys

import pandas as pd
import pytest

from kpstudy.cli import main
from kpstudy.reproduce import PAPER_T_PROB


def test_reproduce_writes_the_t_prob_table(tmp_path):
    assert (
        main(
            [
                "reproduce",
                "--profile",
                "quick",
                "--out",
                str(tmp_path),
                "--images",
                "2",
                "--samples",
                "20",
            ]
        )
        == 0
    )
    tables = tmp_path / "quick" / "tables"
    df = pd.read_csv(tables / "t_prob.csv")
    assert len(df) == 12 and set(zip(df.kappa, df.alpha)) == set(PAPER_T_PROB)
    assert df.soundness.between(0, 1).all() and df.completeness.between(0, 1).all()
    assert (df.samples == 40).all()
    assert "paper_soundness" in (tables / "t_prob.md").read_text()
    assert not list(tables.glob(".*.tmp"))  # no leftovers of the atomic writes


@pytest.mark.parametrize(
    "args, message",
    [
        (["--profile", "huge"], "profile: expected one of"),
        (["--images", "0"], "images: expected a positive integer"),
    ],
)
def test_bad_arguments_exit_non_zero_and_write_nothing(tmp_path, args, message):
    proc = subprocess.run(
        [sys.executable, "-m", "kpstudy", "reproduce", "--out", str(tmp_path), *args],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not any(tmp_path.iterdir())
