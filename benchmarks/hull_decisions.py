"""The pose-bound method on a study's object hulls, model beside model: how many it decides.

On the data and models of a results folder (``--results``, e.g. ``results/quick``), runs
the T-local grid's object hulls (the first ``--seeds`` seed images, hull sizes ``--ms``,
apart and overlapping, at ``--alphas``, κ = 1: the method's verdicts do not depend on κ)
through the pose-bound method with the zonotope, ``--start-splits`` splits per perturbed
image before the first bounds, a node budget and a cap of ``--timeout`` seconds per hull,
one campaign per model (``--models``) in fresh stores under ``--work``. Prints one JSON
line: per model, the records, holds / violated / unknown, the share decided within each
of ``--within`` seconds (of all records), and the median and largest seconds per hull.

    .venv/bin/python -m benchmarks.hull_decisions --results results/quick [--models cnn]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import emit  # noqa: E402


def summarise(records, within) -> dict:
    """Counts, the share decided within each of ``within`` seconds, and seconds per hull."""
    status, seconds = records["pb_status"], records["pb_time"]
    decided = status.isin(["holds", "violated"])
    out = {"records": len(records)}
    out.update({s: int((status == s).sum()) for s in ("holds", "violated", "unknown")})
    for limit in within:
        out[f"decided_within_{limit:g}s"] = round(float((decided & (seconds <= limit)).mean()), 3)
    out["median_seconds"] = round(float(seconds.median()), 2)
    out["max_seconds"] = round(float(seconds.max()), 2)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="results/quick", help="a results folder")
    parser.add_argument("--models", nargs="+", default=["cnn", "cnn_patch_smooth"])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--ms", type=int, nargs="+", default=[2, 3, 4])
    parser.add_argument("--alphas", type=float, nargs="+", default=[1.0, 1.5])
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per hull, a cap")
    parser.add_argument("--nodes", type=int, default=768, help="node budget per hull")
    parser.add_argument("--refine-nodes", type=int, default=64)
    parser.add_argument("--start-splits", type=float, default=1.75)
    parser.add_argument("--within", type=float, nargs="+", default=[60.0, 600.0])
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--work", default="/tmp/kpstudy-decisions", help="scratch folder")
    args = parser.parse_args(argv)
    from kpstudy.study.campaign import run_study

    source, work = Path(args.results), Path(args.work)
    models = {name: source / "models" / f"{name}.pt" for name in args.models}
    missing = [str(p) for p in models.values() if not p.is_file()]
    if not (source / "data").is_dir() or missing:
        what = missing or [str(source / "data")]
        parser.exit(2, f"hull_decisions: error: results: missing {', '.join(what)}\n")
    settings = dict(
        pose_bound_method="zonotope",
        pose_bound_timeout=args.timeout,
        pose_bound_nodes=args.nodes,
        pose_bound_start_splits=args.start_splits,
        pose_bound_refine_nodes=args.refine_nodes,
    )
    grid = dict(alphas=args.alphas, kappas=[1.0], seeds=args.seeds, ms=args.ms)
    out = {"timeout": args.timeout, "nodes": args.nodes, "models": {}}
    for name, path in models.items():
        folder = work / name
        if folder.exists():
            shutil.rmtree(folder)
        records = run_study(
            {name: str(path)},
            source / "data",
            ["objects"],
            folder,
            grid_options=grid,
            pose_bound={name: settings},
            method="forward",
            nodes=1,
            timeout=10.0,
            workers=args.workers,
        )
        out["models"][name] = summarise(records, args.within)
    return emit("pose_bound_hull_decisions", out)


if __name__ == "__main__":
    main()
