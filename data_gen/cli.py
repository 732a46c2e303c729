"""Command line: ``python -m data_gen dataset|perturb|gallery …``.

Bad arguments print ``data_gen <command>: error: …`` naming the argument and exit
with status 2, before anything is written. Ctrl-C exits with status 130 and one line
(an interrupted ``dataset`` or ``perturb`` resumes when run again).
"""

from __future__ import annotations

import argparse
import sys

from kpstudy.cli import interrupted


def main(argv=None) -> int:
    """Run one ``python -m data_gen`` command.

    Parameters
    ----------
    argv : list of str, optional
        The arguments after ``data_gen`` (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0, or 130 after Ctrl-C (bad arguments exit with 2).
    """
    parser = argparse.ArgumentParser(prog="data_gen", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    ds = sub.add_parser(
        "dataset", help="render a COCO keypoint dataset of overhead airplane images"
    )
    ds.add_argument("--out", required=True, help="output folder (empty or absent)")
    ds.add_argument("--n", type=int, required=True, help="number of images")
    ds.add_argument("--size", default="640x400", help="WIDTHxHEIGHT (default 640x400)")
    ds.add_argument("--seed", type=int, default=0)
    ds.add_argument(
        "--variant", default="airliner", help="built-in airplane (airliner, swept, stretched)"
    )
    ds.add_argument("--mesh", help="a user's airplane mesh (OBJ/GLB/PLY) instead of --variant")
    ds.add_argument("--keypoints", help="the user's keypoint JSON (with --mesh)")
    ds.add_argument("--hfov", type=float, default=50.0, help="horizontal field of view, degrees")
    ds.add_argument("--workers", type=int, default=1)
    ds.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")

    pt = sub.add_parser("perturb", help="make a perturbation set of a dataset's test images")
    pt.add_argument("--data", required=True, help="dataset folder")
    pt.add_argument("--kind", required=True, help="objects, blocks, brightness or contrast")
    pt.add_argument(
        "--seeds", type=int, default=10, help="number of seed images from the test split"
    )
    pt.add_argument("--seed", type=int, default=0)
    pt.add_argument(
        "--per-seed", type=int, help="perturbed images per seed image (20 objects, 4 blocks)"
    )
    pt.add_argument(
        "--input-size", type=int, default=64, help="model input side for blocks/brightness/contrast"
    )
    pt.add_argument("--levels", type=float, nargs="+", help="brightness b or contrast c values")
    pt.add_argument(
        "--overlapping-share",
        type=float,
        help="objects: share of each seed's patches centred on the airplane, in [0, 1] "
        "(default: all at random places)",
    )
    pt.add_argument("--overwrite", action="store_true", help="replace an existing set of this kind")

    ga = sub.add_parser("gallery", help="draw renders, occluders and perturbations to PNG figures")
    ga.add_argument(
        "--data", help="dataset folder (renders and perturbations); occluders only without it"
    )
    ga.add_argument("--out", required=True, help="folder for the figures")

    args = parser.parse_args(argv)
    try:
        if args.command == "dataset":
            from data_gen.dataset import generate_dataset

            generate_dataset(
                args.out,
                args.n,
                args.size,
                args.seed,
                args.variant,
                workers=args.workers,
                overwrite=args.overwrite,
                hfov=args.hfov,
                mesh=args.mesh,
                keypoints_json=args.keypoints,
            )
        elif args.command == "perturb":
            from data_gen.perturb import make_perturbations

            out = make_perturbations(
                args.data,
                args.kind,
                seeds=args.seeds,
                seed=args.seed,
                per_seed=args.per_seed,
                input_size=args.input_size,
                levels=args.levels,
                overwrite=args.overwrite,
                overlapping_share=args.overlapping_share,
            )
            print(f"{args.kind} perturbations written to {out}")
        else:
            from data_gen.gallery import write_gallery

            for path in write_gallery(args.out, args.data):
                print(path)
    except (
        ValueError,
        FileNotFoundError,
        FileExistsError,
        NotADirectoryError,
        PermissionError,
    ) as exc:
        parser.exit(2, f"data_gen {args.command}: error: {exc}\n")
    except KeyboardInterrupt:  # Ctrl-C: one line and 128 + SIGINT, no traceback
        return interrupted(f"data_gen {args.command}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
