"""kpstudy.verify.spec: the argmax output spec."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpstudy.verify import ArgmaxSpec


def test_spec_margins_and_paper_polytope_agree():
    spec = ArgmaxSpec([4, 3, 2], [2, None, 0])
    assert spec.n_rows == 3 + 1 and spec.n_outputs == 9
    A, b = spec.to_polytope(big_m=1e6)
    rng = np.random.default_rng(0)
    for _ in range(200):
        y = torch.from_numpy(rng.integers(-3, 4, 9).astype(float))[None]
        in_polytope = bool(np.all(A @ y[0].numpy() <= b))
        assert in_polytope == bool((spec.margins(y) >= 0).all())  # the paper's rows are ≤
    groups = spec.group_min(spec.margins(torch.arange(9.0)[None]))
    assert groups[0, 1] == float("inf")  # excluded group: no rows


def test_spec_bad_input_is_named():
    with pytest.raises(ValueError, match=r"targets\[1\]: expected None or an integer in \[0, 2\)"):
        ArgmaxSpec([3, 2], [0, 2])
    with pytest.raises(ValueError, match="targets: expected one entry per group"):
        ArgmaxSpec([3, 2], [0])
    with pytest.raises(ValueError, match=r"group_sizes\[0\]: expected an integer >= 1"):
        ArgmaxSpec([0, 2], [0, 0])
