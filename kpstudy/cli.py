"""Command line: ``python -m kpstudy
reproduce|compare|train|evaluate|campaign|export-benchmark``. Bad arguments exit with status
2 and a message naming the argument."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def interrupted(prog: str) -> int:
    """Answer Ctrl-C (SIGINT), called while its ``KeyboardInterrupt`` is handled: end the
    progress bars' lines, write ``<prog>: interrupted`` on stderr at the start of a line of
    its own and return 130 (128 + SIGINT, as a shell reports it).

    An open bar is closed (tqdm draws its last state and ends the line, or clears it). Two
    bars whose ``close`` would leave the line open get the line end themselves: one that
    Ctrl-C stopped while it drew its first state (it has no start time yet, so ``close``
    takes it for never shown) and one that Ctrl-C stopped inside its own ``close``, between
    its last state and its line end (it is closed already)."""
    from tqdm import tqdm

    with tqdm.get_lock():
        cut = [bar for bar in _closing_bars(sys.exc_info()[2]) if bar.disable]
        for bar in list(getattr(tqdm, "_instances", ())):
            if bar.disable:
                continue
            if hasattr(bar, "start_t"):
                bar.close()
                continue
            if hasattr(bar, "sp"):  # its screen printer exists: its first state may show
                cut.append(bar)
            try:
                bar.close()  # only forgets it: tqdm saw no start time
            except AttributeError:  # stopped between its two clock readings
                pass
        for bar in cut:
            bar.fp.write("\n")
            bar.fp.flush()
    print(f"{prog}: interrupted", file=sys.stderr, flush=True)
    return 130


def _closing_bars(tb) -> list:
    """The tqdm bars whose ``close`` the traceback ``tb`` passes through."""
    from tqdm import tqdm

    bars = []
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code is tqdm.close.__code__:
            bars.append(frame.f_locals.get("self"))
        tb = tb.tb_next
    return [bar for bar in bars if isinstance(bar, tqdm)]


def _interruptible(run):
    """``run`` that answers Ctrl-C with :func:`interrupted` instead of a traceback."""

    def wrapper(argv=None) -> int:
        try:
            return run(argv)
        except KeyboardInterrupt:
            return interrupted("kpstudy")

    wrapper.__doc__, wrapper.__name__ = run.__doc__, run.__name__
    return wrapper


@_interruptible
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="kpstudy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="run the study's stages and write results/<profile>/")
    rep.add_argument(
        "--profile", default="quick", help="quick (default, the smoke test), standard or paper"
    )
    rep.add_argument("--out", default="results", help="results root folder")
    rep.add_argument("--images", type=int, help="override T-prob's number of views")
    rep.add_argument("--samples", type=int, help="override the Monte Carlo samples per view")
    rep.add_argument("--seeds", type=int, help="override the seed images per campaign")
    rep.add_argument("--timeout", type=float, help="override the seconds per CNN instance")
    rep.add_argument("--workers", type=int, help="local processes per campaign")
    rep.add_argument("--stages", nargs="+", help="data, train, notebooks, report (default all)")
    rep.add_argument(
        "--notebooks",
        nargs="+",
        help="run only these notebooks of the notebooks stage, e.g. 06_local (default all)",
    )
    rep.add_argument("--scheduler", help="Dask scheduler address for the campaigns")
    rep.add_argument(
        "--retrain",
        nargs="+",
        default=(),
        metavar="MODEL",
        help="train these models (cnn_patch_smooth, resnet18) instead of copying their "
        "shipped checkpoints",
    )

    from kpstudy.models.training import CERTIFIED_GROUP, CERTIFIED_WEIGHT, TrainConfig
    from kpstudy.study.campaign import InstanceErrors, add_arguments

    cmp = sub.add_parser(
        "compare",
        help="what differs between two results folders of a profile (tables, timing "
        "columns aside, and model weights); exit status 1 when anything does",
    )
    cmp.add_argument("a", help="a results folder, e.g. results/quick")
    cmp.add_argument("b", help="another, e.g. a second run's")
    pub = sub.add_parser(
        "publish",
        help="copy a run's report, tables and figures into a reference folder stamped with "
        "the commit and command that made them",
    )
    pub.add_argument("run", help="a results folder, e.g. results/standard")
    pub.add_argument("dest", help="the reference folder, e.g. docs/results/standard (replaced)")
    pub.add_argument(
        "--commit", help="git commit of the code that ran (default: the run's runs.jsonl)"
    )
    pub.add_argument(
        "--command",
        dest="run_command",
        help="the command line that ran it (default: the run's runs.jsonl)",
    )
    tr = sub.add_parser("train", help="train a heatmap backbone on a data_gen dataset")
    tr.add_argument("--data", required=True, help="dataset folder (python -m data_gen dataset)")
    tr.add_argument("--out", required=True, help="checkpoint file; resumed when it exists")
    add_arguments(tr, TrainConfig)  # every models.training.TrainConfig field with help
    tr.add_argument("--threads", type=int, help="torch CPU threads (default: all cores)")
    tr.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    tr.add_argument(
        "--init",
        dest="init_checkpoint",
        help="start from this checkpoint's weights (a fine-tuning stage)",
    )
    cert = tr.add_argument_group(CERTIFIED_GROUP)
    cert.add_argument(
        "--certified",
        action="store_true",
        help=f"add the bound term with weight {CERTIFIED_WEIGHT} (--certified-weight sets it)",
    )
    cert.add_argument("--certified-weight", type=float, help="weight of the bound term")
    add_arguments(cert, TrainConfig, CERTIFIED_GROUP)

    ev = sub.add_parser("evaluate", help="keypoint and pose metrics of a trained checkpoint")
    ev.add_argument("--checkpoint", required=True)
    ev.add_argument("--data", required=True, help="dataset folder")
    ev.add_argument("--split", default="test", help="train, val or test (default)")
    ev.add_argument("--out", help="write OUT.csv and OUT.md (summary), OUT_images.csv")

    ca = sub.add_parser("campaign", help="certify a grid of seed images' hulls (resumable)")
    ca.add_argument("--checkpoint", required=True)
    ca.add_argument("--data", required=True, help="dataset folder with perturbations/")
    ca.add_argument("--kind", required=True, help="objects, blocks, brightness or contrast")
    ca.add_argument(
        "--store",
        required=True,
        help="SQLite result store; resumed when it exists, refused when another checkpoint, "
        "dataset, settings or code made it",
    )
    ca.add_argument(
        "--retry-errors",
        action="store_true",
        help="rerun the instances stored with status 'error'",
    )
    ca.add_argument("--alphas", type=float, nargs="+", default=[1.0])
    ca.add_argument("--kappas", type=float, nargs="+", default=[1.0])
    ca.add_argument("--ms", type=int, nargs="+", default=[2], help="hull sizes (local kinds)")
    ca.add_argument("--levels", type=float, nargs="+", help="b or c (global kinds; default all)")
    ca.add_argument("--seeds", type=int, help="first N seed images (default all)")
    add_arguments(ca)  # every campaign.Settings field
    ca.add_argument("--workers", type=int, default=1, help="local processes (default 1)")
    ca.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://10.0.0.1:8786")
    ca.add_argument("--out", help="also write the records as OUT.csv and OUT.md")

    eb = sub.add_parser(
        "export-benchmark",
        help="write a campaign grid's instances as ONNX + VNN-LIB (the VNN-COMP layout)",
    )
    eb.add_argument("--checkpoint", required=True)
    eb.add_argument("--data", required=True, help="dataset folder with perturbations/")
    eb.add_argument("--kind", required=True, help="objects, blocks, brightness or contrast")
    eb.add_argument("--out", required=True, help="benchmark folder; must be new or empty")
    eb.add_argument("--alphas", type=float, nargs="+", default=[1.0])
    eb.add_argument("--kappas", type=float, nargs="+", default=[1.0])
    eb.add_argument("--ms", type=int, nargs="+", default=[2], help="hull sizes (local kinds)")
    eb.add_argument("--levels", type=float, nargs="+", help="b or c (global kinds; default all)")
    eb.add_argument("--seeds", type=int, help="first N seed images (default all)")
    eb.add_argument(
        "--timeout", type=float, default=60.0, help="seconds per instance (instances.csv)"
    )
    eb.add_argument(
        "--input-form",
        default="box",
        help="box (default: u in [0,1]^n, exact hull) or simplex (lambda, sum <= 1)",
    )
    eb.add_argument("--vnnlib-version", default="1.0", help="1.0 (VNN-COMP, default) or 2.0")
    eb.add_argument("--dtype", default="float32", help="float32 (default) or float64 ONNX")
    eb.add_argument(
        "--property-form",
        default="compact",
        help="compact (default: each keypoint's worst margin in the ONNX, one disjunct per "
        "keypoint) or full (the cells as outputs, one disjunct per competing cell)",
    )
    eb.add_argument(
        "--tolerance-units",
        default="heatmap",
        help="the allocation's reading: heatmap (default, sound) or paper (larger cells)",
    )
    eb.add_argument(
        "--reference-nodes",
        type=int,
        help="also decide each instance with kpstudy's verify, this node budget, and write "
        "reference.csv (default: no reference)",
    )
    eb.add_argument(
        "--mix",
        type=int,
        help="keep at most this many instances per reference verdict (holds, violated, "
        "unknown), in grid order; needs --reference-nodes",
    )
    args = parser.parse_args(argv)

    try:
        if args.command == "reproduce":
            from kpstudy.io import check_writable
            from kpstudy.study.reproduction import STAGES, profile, reproduce

            prof = profile(
                args.profile,
                images=args.images,
                samples=args.samples,
                seeds=args.seeds,
                timeout=args.timeout,
                workers=args.workers,
            )
            check_writable(Path(args.out) / prof.name, "out")
            out = reproduce(
                prof,
                args.out,
                stages=args.stages or STAGES,
                notebooks=args.notebooks,
                scheduler=args.scheduler,
                retrain=args.retrain,
                command=_command_line(argv),
            )
            print(f"results written to {out}")
        elif args.command == "compare":
            from kpstudy.study.reproduction import compare_results

            found = compare_results(args.a, args.b)
            for rel, what in found.items():
                print(f"{rel}: {what}")
            return int(any(what != "same" for what in found.values()))
        elif args.command == "publish":
            from kpstudy.study.reference import publish

            dest = publish(args.run, args.dest, commit=args.commit, command=args.run_command)
            print(f"reference written to {dest}")
        elif args.command == "train":
            _train(args)
        elif args.command == "evaluate":
            _evaluate(args)
        elif args.command == "export-benchmark":
            _export_benchmark(args, sys.argv[1:] if argv is None else argv)
        else:
            _campaign(args)
    except InstanceErrors as exc:  # records stored, some of them errors: the count, last
        sys.stdout.flush()
        print(f"kpstudy {args.command}: {exc}", file=sys.stderr, flush=True)
        return 1
    except (
        ValueError,
        FileNotFoundError,
        FileExistsError,
        IsADirectoryError,
        NotADirectoryError,
        PermissionError,
    ) as exc:
        parser.exit(2, f"kpstudy {args.command}: error: {exc}\n")
    return 0


def _train(args) -> None:
    from dataclasses import fields

    import torch

    from kpstudy.io import check_output_file
    from kpstudy.models.training import (
        CERTIFIED_WEIGHT,
        TrainConfig,
        check_device,
        load_checkpoint,
        train,
        weights_digest,
    )

    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"threads: expected a positive integer, got {args.threads}")
        torch.set_num_threads(args.threads)
    check_device(args.device)
    check_output_file(args.out, "out")  # before an epoch of work, not after it
    if args.certified_weight is None:
        args.certified_weight = CERTIFIED_WEIGHT if args.certified else 0.0
    args.init = None
    if args.init_checkpoint is not None:
        try:
            args.init = weights_digest(load_checkpoint(args.init_checkpoint)[1]["model"])
        except (FileNotFoundError, ValueError) as exc:  # it names "checkpoint"
            raise ValueError(f"init: {str(exc).removeprefix('checkpoint: ')}") from None
    config = TrainConfig(**{f.name: getattr(args, f.name) for f in fields(TrainConfig)})
    state = train(args.data, args.out, config, init=args.init_checkpoint, device=args.device)
    print(json.dumps(state["history"][-1]))


def _evaluate(args) -> None:
    import pandas as pd

    from kpstudy.io import check_writable, write_table, write_text_atomic
    from kpstudy.models.evaluation import evaluate

    if args.out:  # OUT.csv, OUT.md and OUT_images.csv go beside each other
        check_writable(Path(args.out).parent, "out")
    summary, per_image = evaluate(args.checkpoint, args.data, args.split)
    if args.out:
        write_table(summary, args.out)
        write_text_atomic(f"{args.out}_images.csv", per_image.to_csv(index=False))
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(summary.to_string(index=False))


def _campaign(args) -> None:
    """Run a campaign; instances that fail are stored as ``error`` (a line each on stderr)
    and the rest go on; if any of the grid's records is an error, the stored ones are
    listed too and :class:`~kpstudy.study.campaign.InstanceErrors` ends the command (exit
    status 1, the count on the last line). An unreadable checkpoint, dataset or
    perturbation set, a store made by another checkpoint, data, settings or code or held by
    a running campaign, an unusable ``--store`` / ``--out`` or an unreachable
    ``--scheduler`` is refused before any work, with nothing written."""
    import pandas as pd
    from tqdm.auto import tqdm

    from kpstudy.io import check_output_file, write_table
    from kpstudy.study.campaign import InstanceErrors, ResultStore, Settings, run_campaign

    if args.out:  # OUT.csv and OUT.md, checked before the work
        check_output_file(Path(f"{args.out}.csv"), "out")
    settings = Settings.from_arguments(args)
    instances = _grid(args)

    listed = set()

    def report(instance, record):
        if record.get("status") == "error":
            listed.add(instance.key)
            tqdm.write(f"kpstudy campaign: {instance.key}: {record['error']}", file=sys.stderr)

    frame = run_campaign(
        instances,
        args.store,
        settings,
        workers=args.workers,
        scheduler=args.scheduler,
        on_record=report,
        retry_errors=args.retry_errors,
    )
    if args.out:
        write_table(frame, args.out)
    if not len(frame):
        print("no instances")
        return
    counts = {"allocation method": frame["status"]}
    if "pb_status" in frame and frame["pb_status"].notna().any():
        counts["pose-bound method"] = frame["pb_status"]
    print(pd.DataFrame({k: v.value_counts() for k, v in counts.items()}).fillna(0).astype(int))
    errors = int((frame["status"] == "error").sum())
    if errors:
        stored = ResultStore(args.store).keys()
        done = [i for i in dict.fromkeys(instances) if i.key in stored]  # frame's rows
        sys.stdout.flush()
        for instance, (_, row) in zip(done, frame.iterrows()):
            if row["status"] == "error" and instance.key not in listed:
                print(f"kpstudy campaign: {instance.key}: {row['error']}", file=sys.stderr)
        raise InstanceErrors(
            f"{errors} of {len(frame)} instances ended 'error' (listed above); rerun them with "
            "--retry-errors"
        )


def _command_line(argv) -> str:
    """This invocation as a command line: ``python -m kpstudy ARGS``."""
    import shlex

    return shlex.join(
        ["python", "-m", "kpstudy", *map(str, sys.argv[1:] if argv is None else argv)]
    )


def _grid(args) -> list:
    """The instances ``--data``, ``--kind`` and the grid options name
    (:func:`kpstudy.study.campaign.grid`)."""
    from kpstudy.study.campaign import grid

    return grid(
        args.data,
        args.kind,
        alphas=args.alphas,
        kappas=args.kappas,
        ms=args.ms,
        levels=args.levels,
        seeds=args.seeds,
    )


def _export_benchmark(args, argv) -> None:
    """Export the grid's instances; bad input (a missing checkpoint, an unknown kind, an
    ``--out`` that is a file or a non-empty folder, …) is refused before anything is
    written."""
    from kpstudy.study.vnncomp import export_benchmark

    if not Path(args.checkpoint).is_file():
        raise FileNotFoundError(f"checkpoint: no file at {args.checkpoint}")
    if not Path(args.data, "annotations.json").is_file():
        raise FileNotFoundError(f"data: no data_gen dataset at {args.data}")
    instances = _grid(args)
    done = export_benchmark(
        args.checkpoint,
        args.data,
        args.out,
        instances,
        timeout=args.timeout,
        input_form=args.input_form,
        vnnlib_version=args.vnnlib_version,
        dtype=args.dtype,
        property_form=args.property_form,
        tolerance_units=args.tolerance_units,
        reference_nodes=args.reference_nodes,
        mix=args.mix,
        command=_command_line(argv),
    )
    for name, reason in done["skipped"]:
        print(f"kpstudy export-benchmark: left out {name}: {reason}", file=sys.stderr)
    print(f"{len(done['written'])} instances written to {done['out']}")


if __name__ == "__main__":
    sys.exit(main())
