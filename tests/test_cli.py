import subprocess
import sys

import pytest


@pytest.mark.parametrize(
    "args, message",
    [
        (["--profile", "huge"], "profile: expected one of"),
        (["--images", "0"], "images: expected a positive number"),
        (["--seeds", "500"], "seeds: expected at most perturbed_seeds=8"),
        (["--stages", "data", "fly"], "stages: expected some of"),
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
