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
from matplotlib.patches import Circle  # noqa: E402

from data_gen.dataset import load_coco, read_image  # noqa: E402
from data_gen.occluders import FAMILIES, occluder_catalog  # noqa: E402
from data_gen.patches import PatchRenderer  # noqa: E402
from data_gen.perturb import KINDS, hull_vertices, load_perturbations  # noqa: E402
from data_gen.render import Light  # noqa: E402
from kpstudy.io import save_figure  # noqa: E402


def plot_renders(data_dir, count: int = 6, names: bool = True, seed: int = 0) -> plt.Figure:
    """A grid of ``count`` renders with their keypoints (red: visible, blue: hidden); with
    ``names``, each keypoint's number is placed clear of the other labels
    (:func:`place_labels`, a leader line back to its point) and a legend below the grid
    names the numbers."""
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
        for u, v, flag in kp:
            ax.plot(
                u, v, "o", ms=3.5, mec="k", mew=0.4, color="red" if flag == 2 else "deepskyblue"
            )
        if names:
            px_per_inch = image["width"] / 6.4  # the panel is about 6.4 in wide
            labels = [str(i) for i in range(len(kp))]
            box = (0.14 * px_per_inch, 0.13 * px_per_inch)  # a 6 pt number in its bbox
            centres = place_labels(kp[:, :2], box, radius=0.13 * px_per_inch)
            for (u, v, _), (x, y), label in zip(kp, centres, labels):
                ax.annotate(
                    label,
                    (u, v),
                    xytext=(x, y),
                    textcoords="data",
                    ha="center",
                    va="center",
                    fontsize=6,
                    color="yellow",
                    bbox=dict(boxstyle="round,pad=0.1", fc="black", alpha=0.55, lw=0),
                    arrowprops=dict(arrowstyle="-", color="yellow", lw=0.5, shrinkA=0, shrinkB=0),
                )
        ax.set_title(f"image {image['id']} ({image['split']})", fontsize=9)
    if names:
        legend = "   ".join(f"{i}\u00a0{name}" for i, name in enumerate(names_list))
        fig.text(0.5, 0.005, _wrap(legend, 170), ha="center", va="bottom", fontsize=8)
        fig.tight_layout(rect=(0, 0.06, 1, 1))
    else:
        fig.tight_layout()
    return fig


def place_labels(points, box, radius: float) -> np.ndarray:
    """Centres for one label per point, clear of each other and of the points.

    Greedy, in the order of ``points``: each label takes, among 16 directions on rings of
    ``radius``, ``2·radius`` … ``4·radius`` around its point, the first position with
    the fewest overlaps with the labels already placed, then with the fewest points
    under it, then the nearest ring.

    Parameters
    ----------
    points : array_like, shape (K, 2)
        The labelled points ``(u, v)``, pixels.
    box : (float, float)
        A label's width and height, pixels.
    radius : float
        The first ring's distance from its point, pixels (> 0).

    Returns
    -------
    ndarray, shape (K, 2)
        The labels' centres, pixels.
    """
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points: expected shape (K, 2), got {pts.shape}")
    w, h = (float(b) for b in box)
    if not (w > 0 and h > 0 and radius > 0):
        raise ValueError(f"box, radius: expected positive sizes, got {box!r}, {radius!r}")
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    rings = [
        (ring, radius * ring * np.stack([np.cos(angles), np.sin(angles)], 1))
        for ring in (1, 2, 3, 4)
    ]
    placed = np.empty((0, 2))
    for p in pts:
        best, best_cost = None, None
        for ring, offsets in rings:
            for centre in p + offsets:
                overlaps = np.sum(
                    (np.abs(placed[:, 0] - centre[0]) < w) & (np.abs(placed[:, 1] - centre[1]) < h)
                )
                covered = np.sum(
                    (np.abs(pts[:, 0] - centre[0]) < w / 2 + 1)
                    & (np.abs(pts[:, 1] - centre[1]) < h / 2 + 1)
                )
                cost = (int(overlaps), int(covered), ring)
                if best_cost is None or cost < best_cost:
                    best, best_cost = centre, cost
        placed = np.vstack([placed, best])
    return placed


def _wrap(text: str, width: int) -> str:
    """``text`` broken at spaces into lines of at most ``width`` characters."""
    import textwrap

    return "\n".join(textwrap.wrap(text, width, break_long_words=False, break_on_hyphens=False))


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
    """One seed image with each stored perturbation kind: its hull's vertices and a point
    inside, each with its difference from the seed (:func:`perturbation_sheet`)."""
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
    return perturbation_sheet(rows)


#: A vertex whose changed pixels cover at most this fraction of the image gets a circle.
_LOCAL_CHANGE = 0.25


def perturbation_sheet(rows, seed: int = 0) -> plt.Figure:
    """Hull vertices and their difference from the seed image, two figure rows per hull.

    Parameters
    ----------
    rows : list of (str, array_like)
        ``(label, vertices)`` per hull, ``vertices`` of shape ``(n + 1, H, W, 3)`` in
        [0, 255] with the seed image first (:func:`data_gen.perturb.hull_vertices`).
    seed : int
        Seed of the random point inside each hull (Dirichlet weights).

    Returns
    -------
    matplotlib.figure.Figure
        Per hull, a row of images (the seed, each vertex, a point inside the hull) and
        below it ``|image − seed|`` (the largest over the channels, grey levels) on one
        colour scale per hull, from 0 to the hull's largest difference, named in the
        titles with the number of pixels changed (by more than half a grey level). A local
        change (at most a quarter of the pixels) is circled in red on the vertex and on its
        difference, so that a small occluder or a 3 × 3 block is found at a glance.
    """
    if not rows:
        raise ValueError("rows: expected one or more (label, vertices) pairs")
    rng = np.random.default_rng(seed)
    hulls = []
    for label, vertices in rows:
        v = np.asarray(vertices, np.float64)
        if v.ndim != 4 or v.shape[0] < 2 or v.shape[-1] != 3:
            raise ValueError(
                f"rows: expected vertices of shape (n + 1, H, W, 3) for {label!r}, got {v.shape}"
            )
        weights = rng.dirichlet(np.ones(len(v)))
        hulls.append((label, [*v, np.tensordot(weights, v, axes=1)]))
    cols = max(len(shown) for _, shown in hulls)
    fig, axes = plt.subplots(
        2 * len(hulls), cols, figsize=(3.0 * cols, 2.2 * 2 * len(hulls)), squeeze=False
    )
    for ax in axes.ravel():
        ax.axis("off")
    for r, (label, shown) in enumerate(hulls):
        seed_image = shown[0]
        diffs = [np.abs(image - seed_image).max(axis=-1) for image in shown]
        top = max(float(d.max()) for d in diffs) or 1.0
        for c, (image, diff) in enumerate(zip(shown, diffs)):
            ax, below = axes[2 * r, c], axes[2 * r + 1, c]
            ax.imshow(np.clip(image, 0, 255).astype(np.uint8), interpolation="nearest")
            last = c == len(shown) - 1
            title = "seed" if c == 0 else ("in the hull" if last else f"vertex {c}")
            ax.set_title(f"{label}: {title}" if c == 0 else title, fontsize=7)
            if c == 0:
                note = f"below: |image − seed|\n(largest over RGB)\n0 – {top:.3g} grey levels"
                below.text(
                    0.5, 0.5, note, ha="center", va="center", fontsize=7,
                    transform=below.transAxes,
                )  # fmt: skip
                continue
            below.imshow(diff, cmap="magma", vmin=0, vmax=top, interpolation="nearest")
            changed = diff > 0.5
            below.set_title(
                f"|Δ| ≤ {diff.max():.3g} on {changed.sum()} px ({changed.mean():.2%})",
                fontsize=6.5,
            )
            if 0 < changed.mean() <= _LOCAL_CHANGE:
                for circle in change_circles(changed):
                    for target in (ax, below):
                        target.add_patch(
                            Circle(circle[:2], circle[2], fill=False, ec="red", lw=1.5)
                        )
    fig.tight_layout()
    return fig


def change_circles(changed, max_circles: int = 8) -> np.ndarray:
    """Circles around the changed areas of an image: one per group of changed pixels
    (pixels within 3 of each other join a group), at most ``max_circles`` (the largest
    groups).

    Parameters
    ----------
    changed : array_like of bool, shape (H, W)
        The changed pixels.

    Returns
    -------
    ndarray, shape (n, 3)
        ``(column, row, radius)`` per circle, pixels: centred on the group's bounding box,
        1.25 × its half-diagonal and at least 6 % of the image's larger side, so that a few
        pixels stay visible.
    """
    from scipy import ndimage

    mask = np.asarray(changed, bool)
    if mask.ndim != 2:
        raise ValueError(f"changed: expected an (H, W) mask, got shape {mask.shape}")
    groups, n = ndimage.label(ndimage.binary_dilation(mask, iterations=3) if mask.any() else mask)
    circles = []
    for box in ndimage.find_objects(groups)[:n]:
        inside = mask[box]
        if not inside.any():
            continue
        rows, cols = np.nonzero(inside)
        r0, r1 = rows.min() + box[0].start, rows.max() + box[0].start
        c0, c1 = cols.min() + box[1].start, cols.max() + box[1].start
        half = 0.5 * np.hypot(r1 - r0 + 1, c1 - c0 + 1)
        radius = max(1.25 * half, 0.06 * max(mask.shape))
        circles.append(((c0 + c1) / 2, (r0 + r1) / 2, radius, inside.sum()))
    circles.sort(key=lambda c: -c[3])
    return np.array([c[:3] for c in circles[:max_circles]], np.float64).reshape(-1, 3)


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
