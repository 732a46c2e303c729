"""`python -m kpstudy reproduce`: the study's stages at a chosen scale, results under results/.

Stages so far:

* **Data** (paper §7.1): a rendered COCO dataset of the airliner (data_gen), the
  perturbation sets of its test seed images (objects, blocks, brightness, contrast)
  and the gallery figures (renders, occluders, perturbations). Reused when a run with
  the same settings already made it.
* **T-prob** (paper Table 2): probabilistic soundness and completeness of the optimal
  tolerance allocation over κ × α, on ground-truth keypoints of overhead views of the
  canonical 23-keypoint airliner (640×400 images, 64×64 heatmaps as for the CNN).

Each stage writes CSV and Markdown tables with the paper's numbers beside ours.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.geometry import project_batch
from kpstudy.io import write_table, write_text_atomic
from kpstudy.montecarlo import soundness_completeness_table

#: Paper Table 2 (soundness, completeness) by (κ, α); "<6.67e-9" is entered as 0.
PAPER_T_PROB = {
    (1.0, 0.5): (1.0, 1.93e-6),
    (1.0, 1.0): (0.998978, 3.07e-5),
    (1.0, 1.5): (0.996596, 4.85e-5),
    (1.0, 2.0): (0.988339, 6.20e-5),
    (1.5, 0.5): (1.0, 0.0),
    (1.5, 1.0): (0.999993, 1.00e-6),
    (1.5, 1.5): (0.999887, 2.00e-6),
    (1.5, 2.0): (0.999890, 3.67e-6),
    (2.0, 0.5): (1.0, 0.0),
    (2.0, 1.0): (1.0, 0.0),
    (2.0, 1.5): (1.0, 3.33e-7),
    (2.0, 2.0): (0.999999, 6.67e-7),
}


@dataclass(frozen=True)
class Profile:
    name: str
    images: int
    samples: int
    kappas: tuple[float, ...] = (1.0, 1.5, 2.0)
    alphas: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0)
    image_size: tuple[int, int] = (640, 400)
    heatmap_size: int = 64
    hfov_deg: float = 70.0
    seed: int = 0
    dataset_images: int = 300
    dataset_size: str = "640x400"
    perturbed_seeds: int = 5


PROFILES = {
    "quick": Profile("quick", images=100, samples=1000),
    "paper": Profile(
        "paper",
        images=3000,
        samples=5000,
        dataset_images=7000,
        dataset_size="1920x1200",
        perturbed_seeds=200,
    ),
}


def reproduce(
    profile: str, out_root="results", *, images: int | None = None, samples: int | None = None
) -> Path:
    """Run every stage of ``profile`` and return its results folder."""
    if profile not in PROFILES:
        raise ValueError(f"profile: expected one of {sorted(PROFILES)}, got {profile!r}")
    prof = PROFILES[profile]
    if images is not None or samples is not None:
        prof = Profile(
            **{
                **asdict(prof),
                "images": prof.images if images is None else images,
                "samples": prof.samples if samples is None else samples,
            }
        )
    for name, value in (("images", prof.images), ("samples", prof.samples)):
        if value < 1:
            raise ValueError(f"{name}: expected a positive integer, got {value}")
    out = Path(out_root) / prof.name
    data(prof, out)
    t_prob(prof, out / "tables")
    return out


def data(prof: Profile, out: Path) -> Path:
    """The dataset, its perturbation sets and the gallery figures under ``out``."""
    from data_gen.dataset import generate_dataset, load_coco
    from data_gen.gallery import write_gallery
    from data_gen.perturb import KINDS, make_perturbations

    folder = out / "data"
    wanted = {"n": prof.dataset_images, "size": prof.dataset_size, "seed": prof.seed}
    try:
        config = load_coco(folder)["info"]["config"]
        have = {
            "n": config["n"],
            "size": "x".join(map(str, config["size"])),
            "seed": config["seed"],
        }
    except FileNotFoundError:
        have = None
    if have != wanted:
        generate_dataset(
            folder, prof.dataset_images, prof.dataset_size, prof.seed, workers=2, overwrite=True
        )
    input_size = prof.heatmap_size
    for kind in KINDS:
        meta = folder / "perturbations" / kind / "meta.json"
        if not meta.is_file() or json.loads(meta.read_text())["config"]["input_size"] != [
            input_size,
            input_size,
        ]:
            make_perturbations(
                folder,
                kind,
                seeds=prof.perturbed_seeds,
                seed=prof.seed,
                input_size=input_size,
                overwrite=True,
            )
    write_gallery(out / "figures", folder)
    return folder


def t_prob(prof: Profile, tables: Path) -> pd.DataFrame:
    """T-prob on ground-truth keypoints of ``prof.images`` random overhead views."""
    P = airliner_keypoints()
    W, H = prof.image_size
    K = intrinsics(W, H, prof.hfov_deg)
    R, t = overhead_poses(prof.images, prof.seed)
    V = project_batch(P, R, t, K)
    scale = (prof.heatmap_size / W, prof.heatmap_size / H)
    start = time.perf_counter()
    df = soundness_completeness_table(
        P,
        V,
        K,
        kappas=prof.kappas,
        alphas=prof.alphas,
        n_samples=prof.samples,
        seed=prof.seed,
        scale=scale,
        max_dv=prof.heatmap_size,
        compile=prof.images >= 1000,
        progress=True,
    )
    df["paper_soundness"] = [
        PAPER_T_PROB.get((k, a), (np.nan,))[0] for k, a in zip(df.kappa, df.alpha)
    ]
    df["paper_completeness"] = [
        PAPER_T_PROB.get((k, a), (np.nan, np.nan))[1] for k, a in zip(df.kappa, df.alpha)
    ]
    write_table(df, tables / "t_prob")
    meta = dict(
        asdict(prof),
        seconds=round(time.perf_counter() - start, 1),
        keypoints="data_gen.keypoints.AIRLINER_KEYPOINTS",
        heatmap_scale=scale,
    )
    write_text_atomic(tables / "t_prob.json", json.dumps(meta, indent=2) + "\n")
    return df
