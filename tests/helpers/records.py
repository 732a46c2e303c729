"""Campaign records made by hand and the Wilson interval written out, for the tests of
kpstudy.study's tables, trends, comparison and report."""

import itertools
import math

import pandas as pd

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval written out (not scipy's): centre ± half-width."""
    centre = (k + z * z / 2) / (n + z * z)
    half = z / (n + z * z) * math.sqrt(k * (n - k) / n + z * z / 4)
    return max(0.0, centre - half), min(1.0, centre + half)


def local_records(pose_bound: bool = True) -> pd.DataFrame:
    """T-local records of two models under two readings, the pose-bound method on the
    'heatmap' reading; m = 2 only, 2 seeds per cell. Statuses depend on the cell so that
    the rates differ: the 'paper' reading holds everywhere; 'heatmap' holds only at
    α = 1.5, refuting at the seed (λ = 0) elsewhere; pb holds unless overlapping."""
    rows = []
    grid = itertools.product(
        ("cnn", "cnn_patch"), ("heatmap", "paper"), (False, True), (1.0, 1.5), (1.0, 1.5)
    )
    for model, units, overlapping, kappa, alpha in grid:
        for seed in range(2):
            holds = units == "paper" or alpha == 1.5
            row = dict(
                model=model,
                tolerance_units=units,
                kind="objects",
                m=2,
                overlapping=overlapping,
                image_id=seed,
                kappa=kappa,
                alpha=alpha,
                status="holds" if holds else "violated",
                time=30.0 if holds else 0.1,
                seed_inside=True,
                counterexample=None if holds else [0.0, 0.0, 0.0],
                dv=[[1, 0]] * 23,
            )
            if pose_bound and units == "heatmap":
                row.update(
                    pb_status="unknown" if overlapping else "holds",
                    pb_time=200.0 if overlapping else 50.0,
                    pb_bound=[1.0] * 6,
                    pb_nonlinear=[1.0] * 6,
                )
            rows.append(row)
    return pd.DataFrame(rows)
