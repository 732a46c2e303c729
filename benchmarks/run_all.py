"""Run every benchmark at its default size; each prints one JSON line (`make bench`)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import bench_allocation, bench_montecarlo, bench_pnp, bench_render, verify_bench  # noqa: E402

if __name__ == "__main__":
    bench_pnp.main(["--compile"])
    bench_allocation.main([])
    bench_montecarlo.main(["--compile"])
    verify_bench.main([])
    bench_render.main([])
