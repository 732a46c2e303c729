"""Command line: ``python -m kpstudy <command>``. Bad arguments exit with status 2."""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="kpstudy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="run the study's stages and write results/<profile>/")
    rep.add_argument("--profile", default="quick", help="quick (default) or paper")
    rep.add_argument("--out", default="results", help="results root folder")
    rep.add_argument("--images", type=int, help="override the profile's number of images")
    rep.add_argument("--samples", type=int, help="override the Monte Carlo samples per image")
    args = parser.parse_args(argv)

    if args.command == "reproduce":
        from kpstudy.reproduce import reproduce

        try:
            out = reproduce(args.profile, args.out, images=args.images, samples=args.samples)
        except ValueError as exc:
            parser.exit(2, f"kpstudy reproduce: error: {exc}\n")
        print(f"results written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
