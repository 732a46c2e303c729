"""Outside VNN-COMP verifiers on an exported benchmark, beside kpstudy's own verdicts.

The benchmark folder is one ``python -m kpstudy export-benchmark … --reference-nodes N``
wrote: ``instances.csv`` (``onnx/NAME.onnx,vnnlib/NAME.vnnlib,TIMEOUT``) and
``reference.csv`` (kpstudy's verdict and seconds per instance). Each peer runs every
instance in a process of its own with ``--timeout`` seconds (its own budget) and is
killed, its whole process group, ``--grace`` seconds later:

* NeuralSAT 0.2.17 (``neuralsat``), in its own environment (``--neuralsat-python``,
  default .venv-neuralsat/bin/python, ``make neuralsat``), through tests/neuralsat_worker.py
  as benchmarks/README.md's "Outside oracle" section and tests/test_neuralsat.py run it:
  ``--device cpu --verbosity 0 --timeout T --setting_file S --result_file R
  --export_cex``, ``S`` = ``{"max_iterations": --neuralsat-iterations}``;
* α,β-CROWN (``abcrown``): ``python abcrown.py --config BASE --onnx_path … --vnnlib_path
  … --timeout T --results_file R --save_adv_example --cex_path …`` in abcrown.py's
  folder (``--abcrown``, ``--abcrown-python``, ``--abcrown-config``; no defaults: without
  ``--abcrown`` the peer is skipped). It reads a copy of the VNN-LIB file in the
  instance's log folder, so the ``*.vnnlib.compiled`` cache it writes beside the file it
  reads stays out of the benchmark folder.

A result file's first line is the answer (``unsat`` → ``holds``, ``sat`` → ``violated``,
anything else → ``unknown``); a ``sat`` may list its counterexample, which is re-checked
in float64 on the torch proxy (:func:`kpstudy.verify.export.check_counterexample`) when the
benchmark's checkpoint and dataset are found (the paths of README.md's command line, or
``--checkpoint`` / ``--data``) and match the SHA-256 digests README.md records. A peer's
seconds are the wall time of its process, start-up included; kpstudy's are
reference.csv's (``verify`` in-process, this machine's seconds when it was exported).
Peak memory: the largest resident set of one process of the instance (GNU time's ``%M``).

JSON (``peer_verifiers``): per peer ``summary`` (``instances``, ``loaded``: answered
without a load or parse error, ``decided``, ``holds``, ``violated``, ``unknown``,
``agreeing`` / ``disagreeing`` with kpstudy where both decided, ``median_s``, ``max_s``,
``decided_within_timeout``, kpstudy's ``kpstudy_median_s`` / ``kpstudy_max_s``,
``speed_ratio`` = peer median ÷ kpstudy median, ``peak_rss_mb``, ``counterexamples``,
``errors``, ``killed``) and ``rows`` (one per instance); ``skipped`` peers with the
reason. Logs and result files go to ``--out`` (default a new temporary folder), the JSON
to ``--out``/peer_verifiers.json too.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

from benchmarks.common import emit
from kpstudy.verify.export import check_counterexample, read_answer

ROOT = Path(__file__).resolve().parents[1]
PEERS = ("neuralsat", "abcrown")
NEURALSAT_WORKER = ROOT / "tests" / "neuralsat_worker.py"
NEURALSAT_PYTHON = ROOT / ".venv-neuralsat" / "bin" / "python"
#: GNU time, which measures a command's peak memory.
TIME = Path("/usr/bin/time")
#: A peer's answer → kpstudy's word; every other answer (timeout, unknown, early_stop, …)
#: is ``unknown``.
VERDICTS = {"unsat": "holds", "sat": "violated"}


def verdict(answer: str) -> str:
    """kpstudy's word for a peer's ``answer``: ``holds``, ``violated`` or ``unknown``."""
    return VERDICTS.get(answer, "unknown")


def read_benchmark(folder) -> list[dict]:
    """The instances of benchmark ``folder`` in instances.csv's order: ``name``, ``onnx``,
    ``vnnlib`` (absolute Paths), ``reference`` (kpstudy's status) and ``reference_s``
    (its seconds). ``FileNotFoundError`` / ``ValueError``, one line naming ``folder``,
    ``instances.csv`` or ``reference.csv``, for a folder without them, a row that names a
    missing file or an instance without a reference row."""
    folder = Path(folder).resolve()
    for name in ("instances.csv", "reference.csv"):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"folder: no {name} in {folder}")
    with open(folder / "reference.csv", newline="") as f:
        reader = csv.DictReader(f)
        if not {"name", "status", "time"} <= set(reader.fieldnames or ()):
            raise ValueError("reference.csv: expected the columns name, status, time")
        reference = {r["name"]: (r["status"], float(r["time"])) for r in reader}
    rows = []
    with open(folder / "instances.csv", newline="") as f:
        for line, fields in enumerate(csv.reader(f), 1):
            if not fields:
                continue
            if len(fields) != 3:
                raise ValueError(f"instances.csv: line {line}: expected ONNX,VNNLIB,TIMEOUT")
            onnx, vnnlib = folder / fields[0].strip(), folder / fields[1].strip()
            for path in (onnx, vnnlib):
                if not path.is_file():
                    raise FileNotFoundError(f"instances.csv: line {line}: no file {path}")
            name = onnx.stem
            if name not in reference:
                raise ValueError(f"reference.csv: no row for {name}")
            status, seconds = reference[name]
            rows.append(
                dict(name=name, onnx=onnx, vnnlib=vnnlib, reference=status, reference_s=seconds)
            )
    if not rows:
        raise ValueError(f"instances.csv: no instances in {folder / 'instances.csv'}")
    return rows


def run_process(command: list, cwd, log, wall: float) -> dict:
    """Run ``command`` in ``cwd`` in a session of its own, stdout and stderr to ``log``,
    under GNU time (:data:`TIME`, where there is one) for its memory; kill its process
    group after ``wall`` seconds, and whatever of the group outlives the process.
    ``seconds`` (wall time), ``exit`` (its status; None when killed), ``killed`` and
    ``peak_rss_mb``: the largest resident set of one process of its tree (GNU time's
    ``%M``), None when killed or without GNU time (``wait4`` of a child forked from this
    process would count this process's own resident set)."""
    memory = Path(log).with_name("memory.txt")
    memory.unlink(missing_ok=True)
    if TIME.is_file():
        command = [TIME, "-f", "%M", "-o", memory, *command]
    start = time.perf_counter()
    with open(log, "wb") as out:
        process = subprocess.Popen(
            [str(c) for c in command],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        process.wait(wall)
        killed = False
    except subprocess.TimeoutExpired:
        _kill_group(process.pid)
        process.wait()
        killed = True
    seconds = time.perf_counter() - start
    _kill_group(process.pid)  # children it left behind
    words = memory.read_text().split() if memory.is_file() and not killed else []
    peak = round(int(words[-1]) / 1024, 1) if words and words[-1].isdigit() else None
    return {
        "seconds": seconds,
        "exit": None if killed else process.returncode,
        "killed": killed,
        "peak_rss_mb": peak,
    }


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def neuralsat_command(args, instance: dict, folder: Path) -> tuple[list, Path, Path]:
    """NeuralSAT's command line on ``instance``, its working folder and result file."""
    settings, result = folder / "settings.json", folder / "result.txt"
    settings.write_text(json.dumps({"max_iterations": args.neuralsat_iterations}))
    command = [args.neuralsat_python, NEURALSAT_WORKER, "--net", instance["onnx"]]
    command += ["--spec", instance["vnnlib"], "--device", "cpu", "--verbosity", "0"]
    command += ["--timeout", args.timeout, "--setting_file", settings, "--result_file", result]
    return command + ["--export_cex"], folder, result


def abcrown_command(args, instance: dict, folder: Path) -> tuple[list, Path, Path]:
    """α,β-CROWN's command line on ``instance`` (a copy of its VNN-LIB file in ``folder``:
    the parsed ``*.compiled`` cache lands beside the copy), its working folder (abcrown.py's)
    and result file."""
    spec, result = folder / instance["vnnlib"].name, folder / "result.txt"
    shutil.copyfile(instance["vnnlib"], spec)
    command = [args.abcrown_python, args.abcrown, "--config", args.abcrown_config]
    command += ["--onnx_path", instance["onnx"], "--vnnlib_path", spec]
    command += ["--timeout", args.timeout, "--results_file", result, "--save_adv_example"]
    command += ["--cex_path", folder / "cex.txt", "--output_file", folder / "out.pkl"]
    return command, args.abcrown.parent, result


COMMANDS = {"neuralsat": neuralsat_command, "abcrown": abcrown_command}


def run_peer(peer: str, args, instance: dict, folder: Path) -> dict:
    """One instance's row for ``peer``: kpstudy's ``reference`` and ``reference_s``, the
    peer's ``answer`` (its result file's first line; ``error`` where it wrote none,
    ``killed`` past the wall limit), ``verdict``, ``seconds``, ``exit``, ``peak_rss_mb``,
    ``x`` (a ``sat`` answer's counterexample, or None) and ``log`` (the last lines of an
    error)."""
    folder.mkdir(parents=True, exist_ok=True)
    command, cwd, result = COMMANDS[peer](args, instance, folder)
    log = folder / "log.txt"
    ran = run_process(command, cwd, log, args.timeout + args.grace)
    answer, x = ("killed", None) if ran["killed"] else ("error", None)
    if not ran["killed"] and result.is_file():
        answer, x = read_answer(result)
        answer = answer or "error"
    row = {
        "name": instance["name"],
        "reference": instance["reference"],
        "reference_s": instance["reference_s"],
        "answer": answer,
        "verdict": verdict(answer),
        **ran,
        "x": x if answer == "sat" else None,
    }
    if answer == "error":
        row["log"] = log.read_text(errors="replace").strip().splitlines()[-5:]
    return row


def summarize(rows: list[dict], timeout: float) -> dict:
    """One peer's figures over its ``rows`` (:func:`run_peer`'s, with ``counterexample``
    where one was re-checked)."""
    decided = [r for r in rows if r["verdict"] != "unknown"]
    both = [r for r in decided if r["reference"] in VERDICTS.values()]
    both_names = {r["name"] for r in both}
    seconds = [r["seconds"] for r in rows]
    ours = [r["reference_s"] for r in rows]
    checked = [r for r in rows if isinstance(r.get("counterexample"), dict)]
    real = {
        r["name"]
        for r in checked
        if r["counterexample"]["inside"] and r["counterexample"]["violates"]
    }
    median, ours_median = statistics.median(seconds), round(statistics.median(ours), 3)
    return {
        "instances": len(rows),
        "loaded": sum(r["answer"] not in ("error", "killed") for r in rows),
        "decided": len(decided),
        **{v: sum(r["verdict"] == v for r in rows) for v in ("holds", "violated", "unknown")},
        "agreeing": sum(r["verdict"] == r["reference"] for r in both),
        "disagreeing": [r["name"] for r in both if r["verdict"] != r["reference"]],
        "decided_where_kpstudy_unknown": [
            r["name"] for r in decided if r["name"] not in both_names
        ],
        "median_s": round(median, 3),
        "max_s": round(max(seconds), 3),
        "decided_within_timeout": sum(r["seconds"] <= timeout for r in decided),
        "kpstudy_median_s": ours_median,
        "kpstudy_max_s": max(ours),
        "speed_ratio": round(median / ours_median, 2) if ours_median > 0 else None,
        "peak_rss_mb": max((r["peak_rss_mb"] for r in rows if r["peak_rss_mb"]), default=None),
        "counterexamples": {
            "given": sum(r["x"] is not None for r in rows),
            "checked": len(checked),
            "real": len(real),
            "not_real": [r["name"] for r in checked if r["name"] not in real],
        },
        "errors": [r["name"] for r in rows if r["answer"] == "error"],
        "killed": [r["name"] for r in rows if r["answer"] == "killed"],
    }


class Rebuilder:
    """The benchmark's instances rebuilt as kpstudy exported them (proxy, hull, spec), from
    the checkpoint and dataset that its README.md names (or ``checkpoint`` / ``data``),
    loaded on first use; :attr:`why_not` says why none can be (no README.md, missing
    files, digests that differ from README.md's)."""

    def __init__(self, folder: Path, checkpoint=None, data=None) -> None:
        self.folder, self.checkpoint, self.data = folder, checkpoint, data
        self.why_not: str | None = None
        self._context = None

    def _sources(self):
        readme = self.folder / "README.md"
        if not readme.is_file():
            raise LookupError(f"no README.md in {self.folder}")
        text = readme.read_text()
        found = re.search(r"Made with\n\n```\n(.*?)\n```", text, re.S)
        words = shlex.split(found[1]) if found else []
        made = argparse.ArgumentParser(add_help=False)
        made.add_argument("--checkpoint")
        made.add_argument("--data")
        named, _ = made.parse_known_args(words)
        paths = []
        for given, recorded, what in (
            (self.checkpoint, named.checkpoint, "checkpoint"),
            (self.data, named.data, "data"),
        ):
            path = given or recorded
            if path is None or not Path(path).exists():
                raise LookupError(f"{what}: {path or 'not in README.md'} not found; give --{what}")
            paths.append(Path(path))
        field = {k: re.search(rf"{k} `([^`]*)`", text) for k in ("tolerance reading", "input form")}
        digests = dict(re.findall(r"- (checkpoint|dataset) `[^`]*`, SHA-256 `([0-9a-f]+)`", text))
        if None in field.values() or len(digests) != 2:
            raise LookupError("README.md lacks the tolerance reading, input form or digests")
        return *paths, field["tolerance reading"][1], field["input form"][1], digests

    def context(self):
        """``(backbone, seed_of, data, hull_seed, tolerance_units, input_form)``, or None."""
        if self._context is None and self.why_not is None:
            from kpstudy.study.campaign import Settings, _context, provenance

            try:
                checkpoint, data, units, form, digests = self._sources()
                settings = Settings(str(checkpoint), str(data), tolerance_units=units)
                origin = provenance(settings)
                for key in ("checkpoint", "dataset"):
                    if origin[key] != digests[key]:
                        raise LookupError(f"the {key}'s SHA-256 differs from README.md's")
                backbone, seed_of = _context(str(checkpoint), str(data))
            except (LookupError, ValueError, FileNotFoundError) as exc:
                self.why_not = str(exc)
                return None
            self._context = (backbone, seed_of, data, settings.hull_seed, units, form)
        return self._context

    def check(self, name: str, x):
        """:func:`kpstudy.verify.export.check_counterexample` of ``x`` on instance ``name`` (its
        ``inside``, ``margin``, ``violates``), or a string saying why it was not checked."""
        from kpstudy.study.campaign import Instance
        from kpstudy.study.vnncomp import _build, instance_name

        context = self.context()
        if context is None:
            return f"not checked: {self.why_not}"
        parts = re.fullmatch(r"([a-z]+)_(\d+)_(?:m(\d+)_(ov|nov)|l([^_]+))_a([^_]+)_k([^_]+)", name)
        if parts is None:
            return "not checked: not an export-benchmark instance name"
        kind, image, m, overlap, level, alpha, kappa = parts.groups()
        instance = Instance(
            kind,
            int(image),
            float(alpha),
            float(kappa),
            m=None if m is None else int(m),
            overlapping=None if overlap is None else overlap == "ov",
            level=None if level is None else float(level),
        )
        if instance_name(instance) != name:
            return "not checked: not an export-benchmark instance name"
        backbone, seed_of, data, hull_seed, units, form = context
        built, reason = _build(backbone, seed_of, data, hull_seed, units, instance)
        if built is None:
            return f"not checked: {reason}"
        if len(x) != built.hull.n:
            return f"not checked: {len(x)} inputs, the instance has {built.hull.n}"
        found = check_counterexample(built.proxy, built.hull, built.spec, x, form)
        return {k: found[k] for k in ("inside", "margin", "violates")}


def _fail(parser, message: str):
    """End with status 2 and one line, as kpstudy's command line does for bad input."""
    parser.exit(2, f"peer_verifiers: error: {message}\n")


def _file(parser, path, option: str) -> Path:
    if not Path(path).is_file():
        _fail(parser, f"{option}: no file at {path}")
    return Path(path).absolute()  # not resolved: a venv's python is a link out of the venv


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="an export-benchmark folder with reference.csv")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per instance")
    parser.add_argument(
        "--grace", type=float, default=30.0, help="seconds past --timeout before a kill"
    )
    parser.add_argument("--peers", nargs="+", choices=PEERS, help="default: every one available")
    parser.add_argument("--neuralsat-python", default=str(NEURALSAT_PYTHON))
    parser.add_argument(
        "--neuralsat-iterations", type=int, default=500, help="NeuralSAT's max_iterations"
    )
    parser.add_argument("--abcrown", help="α,β-CROWN's complete_verifier/abcrown.py")
    parser.add_argument("--abcrown-python", help="the interpreter of α,β-CROWN's environment")
    parser.add_argument("--abcrown-config", help="a base YAML config for abcrown.py")
    parser.add_argument("--checkpoint", help="the benchmark's checkpoint (default: README.md's)")
    parser.add_argument("--data", help="the benchmark's dataset (default: README.md's)")
    parser.add_argument("--limit", type=int, help="the first N instances")
    parser.add_argument(
        "--out", help="folder for logs and result files (default: a new temporary one)"
    )
    args = parser.parse_args(argv)
    fail = partial(_fail, parser)
    if not args.timeout > 0 or not args.grace >= 0:
        fail(f"timeout, grace: expected seconds > 0 and >= 0, got {args.timeout}, {args.grace}")
    if args.limit is not None and args.limit < 1:
        fail(f"limit: expected a positive integer, got {args.limit}")
    if args.neuralsat_iterations < 1:
        fail(f"neuralsat-iterations: expected a positive integer, got {args.neuralsat_iterations}")
    try:
        instances = read_benchmark(args.folder)[: args.limit]
    except (FileNotFoundError, ValueError) as exc:
        fail(str(exc))
    skipped = {}
    if not Path(args.neuralsat_python).is_file():
        skipped["neuralsat"] = (
            f"no NeuralSAT environment at {args.neuralsat_python} (`make neuralsat`)"
        )
    if args.abcrown is None:
        skipped["abcrown"] = "no --abcrown given"
    else:
        args.abcrown = _file(parser, args.abcrown, "abcrown")
        for option in ("abcrown_python", "abcrown_config"):
            if getattr(args, option) is None:
                fail(f"{option.replace('_', '-')}: required with --abcrown")
            setattr(args, option, _file(parser, getattr(args, option), option.replace("_", "-")))
    for peer in args.peers or ():
        if peer in skipped:
            fail(f"peers: {peer} is not available: {skipped[peer]}")
    peers = args.peers or [p for p in PEERS if p not in skipped]
    if not peers:
        fail("peers: none available (" + "; ".join(skipped.values()) + ")")
    out = Path(args.out or tempfile.mkdtemp(prefix="peer_verifiers-")).resolve()
    out.mkdir(parents=True, exist_ok=True)

    rebuilder = Rebuilder(Path(args.folder).resolve(), args.checkpoint, args.data)
    results = {}
    for peer in peers:
        rows = []
        for instance in instances:
            row = run_peer(peer, args, instance, out / peer / instance["name"])
            if row["x"] is not None:
                row["counterexample"] = rebuilder.check(instance["name"], row["x"])
            row["x"] = None if row["x"] is None else row["x"].tolist()
            row["seconds"] = round(row["seconds"], 3)
            rows.append(row)
            print(
                f"{peer} {row['name']}: {row['answer']} in {row['seconds']:.1f} s "
                f"(kpstudy {row['reference']})",
                file=sys.stderr,
                flush=True,
            )
        results[peer] = {"summary": summarize(rows, args.timeout), "rows": rows}
    result = emit(
        "peer_verifiers",
        {
            "folder": str(Path(args.folder).resolve()),
            "instances": len(instances),
            "timeout_s": args.timeout,
            "grace_s": args.grace,
            "neuralsat_iterations": args.neuralsat_iterations if "neuralsat" in peers else None,
            "abcrown_config": None if args.abcrown is None else str(args.abcrown_config),
            "out": str(out),
            "peers": results,
            "skipped": {p: why for p, why in skipped.items() if p not in peers},
        },
    )
    (out / "peer_verifiers.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
