"""The quick T-local and T-global tables on a quiet machine and on one held at full load.

Copies (hard links) the data and models of a quick results folder into two fresh results
roots under ``--work``, runs notebooks 06 and 07 there with ``python -m kpstudy
reproduce --profile quick --stages notebooks`` — first alone, then beside ``--load``
busy-loop processes (default: one per core) — and prints one JSON line: each run's wall
seconds, the searches whose time cap (not the node budget) ended them per table
(:func:`kpstudy.study.comparison.capped_searches` over the records), and what
``kpstudy compare`` finds between the two runs' tables (timing columns aside).

    .venv/bin/python -m benchmarks.loaded_tables --results results/quick [--work /tmp/loaded]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import emit  # noqa: E402

NOTEBOOKS = ("06_local", "07_global")
TABLES = ("t_local", "t_global")


def _busy() -> None:
    while True:
        pass


def run_tables(source: Path, root: Path) -> float:
    """Notebooks 06 and 07 of the quick profile in ``root/quick``, on ``source``'s data
    and models (hard links); returns the wall seconds."""
    if root.exists():
        shutil.rmtree(root)
    target = root / "quick"
    target.mkdir(parents=True)
    for part in ("data", "models"):
        shutil.copytree(source / part, target / part, copy_function=os.link)
    command = [sys.executable, "-m", "kpstudy", "reproduce", "--profile", "quick"]
    command += ["--out", str(root), "--stages", "notebooks", "--notebooks", *NOTEBOOKS]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def caps(results: Path) -> dict[str, dict[str, int]]:
    """Per table, ``{cell [method]: searches}`` whose time cap fired."""
    import pandas as pd

    from kpstudy.study.comparison import capped_searches

    return {
        name: capped_searches(pd.read_csv(results / "tables" / f"{name}_records.csv"))
        for name in TABLES
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="results/quick", help="a quick results folder")
    parser.add_argument("--work", default="/tmp/kpstudy-loaded", help="scratch folder")
    parser.add_argument("--load", type=int, default=os.cpu_count(), help="busy processes")
    args = parser.parse_args(argv)
    from kpstudy.study.reproduction import compare_results

    source, work = Path(args.results), Path(args.work)
    if not (source / "data").is_dir() or not (source / "models").is_dir():
        parser.exit(2, f"loaded_tables: error: results: no data/ and models/ in {source}\n")
    quiet_s = run_tables(source, work / "quiet")
    load = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(args.load)]
    for process in load:
        process.start()
    try:
        loaded_s = run_tables(source, work / "loaded")
    finally:
        for process in load:
            process.terminate()
    quiet, loaded = work / "quiet" / "quick", work / "loaded" / "quick"
    found = compare_results(quiet, loaded)
    return emit(
        "quick_tables_quiet_vs_loaded",
        {
            "busy_processes": args.load,
            "quiet_seconds": round(quiet_s, 1),
            "loaded_seconds": round(loaded_s, 1),
            "caps_quiet": caps(quiet),
            "caps_loaded": caps(loaded),
            "compare": {rel: what for rel, what in found.items() if rel.startswith("tables/t_")},
        },
    )


if __name__ == "__main__":
    main()
