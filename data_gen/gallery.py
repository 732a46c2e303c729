"""Figures to look at the data: renders with keypoints, the occluder gallery, perturbations.

Each ``plot_*`` function returns a matplotlib figure; :func:`write_gallery` saves them
as PNGs (``python -m data_gen gallery --data DIR --out FIGDIR``).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from data_gen.dataset import load_coco, read_image  # noqa: E402
from data_gen.occluders import FAMILIES, occluder_catalog  # noqa: E402
from data_gen.patches import PatchRenderer  # noqa: E402
from data_gen.perturb import KINDS, hull_vertices, load_perturbations  # noqa: E402
from data_gen.render import Light  # noqa: E402
from kpstudy.io import save_figure  # noqa: E402


def plot_renders(data_dir, count: int = 6, names: bool = True, seed: int = 0) -> plt.Figure:
    """A grid of ``count`` renders with their keypoints (red: visible, blue: hidden) and names."""
    coco = load_coco(data_dir)
    names_list = coco["categories"][0]["keypoints"]
    rng = np.random.default_rng(seed)
    picks = sorted(
        rng.choice(len(coco["images"]), size=min(count, len(coco["images"])), replace=False)
    )
    cols = min(3, len(picks))
    rows = int(np.ceil(len(picks) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(6.4 * cols, 4.2 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, k in zip(axes.ravel(), picks):
        image, ann = coco["images"][k], coco["annotations"][k]
        ax.imshow(read_image(Path(data_dir) / image["file_name"]))
        kp = np.reshape(ann["keypoints"], (-1, 3))
        for (u, v, flag), name in zip(kp, names_list):
            ax.plot(
                u, v, "o", ms=3.5, mec="k", mew=0.4, color="red" if flag == 2 else "deepskyblue"
            )
            if names:
                ax.annotate(
                    name,
                    (u, v),
                    xytext=(3, 2),
                    textcoords="offset points",
                    fontsize=4.5,
                    color="yellow",
                )
        ax.set_title(f"image {image['id']} ({image['split']})", fontsize=9)
    fig.tight_layout()
    return fig


def plot_occluders(
    px_per_m: float = 24.0, columns: int = 8, family: str | None = None
) -> plt.Figure:
    """The occluders (all, or one ``family``) seen from above at one common scale, with a
    1 m bar."""
    renderer = PatchRenderer()
    light = Light(np.array([0.45, -0.35, 0.82]), sun=0.75, ambient=0.4)
    catalog = occluder_catalog(family)
    rows = int(np.ceil(len(catalog) / columns))
    patches = [renderer.render(o.name, o.mesh, px_per_m, light, yaw=90.0) for o in catalog]
    side = max(max(p.shape[:2]) for p in patches)
    fig, axes = plt.subplots(rows, columns, figsize=(2.2 * columns, 2.7 * rows), squeeze=False)
    background = np.array([112, 112, 116], np.float32)
    colors = dict(zip(FAMILIES, ("tab:orange", "tab:green", "tab:blue")))
    for ax in axes.ravel():
        ax.axis("off")
    for ax, occluder, patch in zip(axes.ravel(), catalog, patches):
        canvas = np.tile(background, (side, side, 1))
        h, w = patch.shape[:2]
        y, x = (side - h) // 2, (side - w) // 2
        a = patch[..., 3:]
        canvas[y : y + h, x : x + w] = canvas[y : y + h, x : x + w] * (1 - a) + patch[..., :3] * a
        ax.imshow(canvas.astype(np.uint8))
        ax.plot([4, 4 + px_per_m], [side - 5, side - 5], color="white", lw=2)
        ax.set_title(occluder.name.replace("_", " "), fontsize=7, color=colors[occluder.family])
    fig.suptitle(
        f"{len(catalog)} {family or 'occluder'}s at {px_per_m:g} px/m (bar: 1 m); "
        + ", ".join(f"{f}: {c[4:]}" for f, c in colors.items()),
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return fig


def plot_perturbations(data_dir, image_id: int | None = None) -> plt.Figure:
    """One seed image with each stored perturbation kind: its hull's vertices and a point inside."""
    kinds = [k for k in KINDS if (Path(data_dir) / "perturbations" / k / "meta.json").is_file()]
    if not kinds:
        raise FileNotFoundError(f"data_dir: no perturbation sets in {data_dir}")
    rows = []
    for kind in kinds:
        meta = load_perturbations(data_dir, kind)["images"]
        ids = sorted({r["image_id"] for r in meta})
        target = image_id if image_id in ids else ids[0]
        if kind in ("objects", "blocks"):
            for overlapping in (False, True):
                n = sum(r["image_id"] == target and r["overlapping"] == overlapping for r in meta)
                if n:
                    label = f"{kind}, {'overlapping' if overlapping else 'non-overlapping'}"
                    rows.append(
                        (label, hull_vertices(data_dir, target, kind, min(n, 3), overlapping))
                    )
        else:
            level = max(r["level"] for r in meta)
            rows.append((f"{kind} ±{level:g}", hull_vertices(data_dir, target, kind, level=level)))
    cols = max(len(v) for _, v in rows) + 1
    fig, axes = plt.subplots(len(rows), cols, figsize=(3.2 * cols, 2.3 * len(rows)), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    rng = np.random.default_rng(0)
    for r, (label, vertices) in enumerate(rows):
        weights = rng.dirichlet(np.ones(len(vertices)))
        shown = [*vertices, np.tensordot(weights, vertices, axes=1)]
        for c, image in enumerate(shown):
            axes[r, c].imshow(np.clip(image, 0, 255).astype(np.uint8), interpolation="nearest")
            title = "seed" if c == 0 else ("in the hull" if c == len(shown) - 1 else f"vertex {c}")
            axes[r, c].set_title(f"{label}: {title}" if c == 0 else title, fontsize=7)
    fig.tight_layout()
    return fig


def write_gallery(out, data_dir=None) -> list[Path]:
    """Save the figures as PNGs in ``out``; renders and perturbations need ``data_dir``."""
    out = Path(out)
    figures = {
        "occluders": plot_occluders,
        "crew_closeup": lambda: plot_occluders(px_per_m=96.0, family="person"),
    }
    if data_dir is not None:
        load_coco(data_dir)
        figures["renders"] = lambda: plot_renders(data_dir)
        if (Path(data_dir) / "perturbations").is_dir():
            figures["perturbations"] = lambda: plot_perturbations(data_dir)
    return [save_figure(make(), out / f"{name}.png") for name, make in figures.items()]


def dataset_summary(data_dir):
    """One row per split and per perturbation set: seed images, images, overlapping and
    non-overlapping images (local kinds) and levels (global kinds)."""
    import pandas as pd

    coco = load_coco(data_dir)
    rows = []
    for split in ("train", "val", "test"):
        n = sum(im.get("split") == split for im in coco["images"])
        rows.append(dict(set=f"{split} split", seeds=None, images=n))
    for kind in KINDS:
        if not (Path(data_dir) / "perturbations" / kind / "meta.json").is_file():
            continue
        meta = load_perturbations(data_dir, kind)["images"]
        row = dict(
            set=f"{kind} perturbations", seeds=len({r["image_id"] for r in meta}), images=len(meta)
        )
        if kind in ("objects", "blocks"):
            row["overlapping"] = sum(bool(r["overlapping"]) for r in meta)
            row["non_overlapping"] = len(meta) - row["overlapping"]
        else:
            row["levels"] = ", ".join(f"{v:g}" for v in sorted({r["level"] for r in meta}))
        rows.append(row)
    columns = ["set", "seeds", "images", "overlapping", "non_overlapping", "levels"]
    frame = pd.DataFrame(rows, columns=columns)
    return frame.astype({c: "Int64" for c in columns[1:5]})
