"""NeuralSAT as a second outside oracle for :func:`kpstudy.verify.verify`, beside Marabou
(tests/test_marabou.py): it reads the exported ONNX + VNN-LIB files with its own readers
and decides them, and every instance that both decide must get the same verdict (``unsat``
⇔ ``holds``, ``sat`` ⇔ ``violated``), each of its counterexamples a point of the hull that
fails in float64 on the torch model.

NeuralSAT 0.2.17 lives in its own environment, .venv-neuralsat (``make neuralsat``,
environment-neuralsat.txt; ``make test`` makes it), as its pins clash with kpstudy's; it
runs as a child process (tests/neuralsat_worker.py), one per instance, with an iteration
budget. Where the environment is missing the module is skipped.
"""

from __future__ import annotations

import csv
import json
import subprocess
import time
from pathlib import Path

import onnx
import pytest
import torch
from torch import nn

from kpstudy.models.pooling import build_cell_pool
from kpstudy.verify import ConvexHull, verify
from kpstudy.verify.export import check_counterexample, export_instance, read_answer
from kpstudy.verify.spec import ArgmaxSpec
from tests.helpers.tiny_proxies import make_instance

ROOT = Path(__file__).resolve().parents[1]
PYTHON = ROOT / ".venv-neuralsat" / "bin" / "python"
WORKER = Path(__file__).with_name("neuralsat_worker.py")

if not PYTHON.is_file():
    pytest.skip(
        f"NeuralSAT's environment {PYTHON.parent.parent.name} is missing: `make neuralsat` "
        "makes it (`make test` does)",
        allow_module_level=True,
    )

pytestmark = [pytest.mark.neuralsat, pytest.mark.slow]

#: NeuralSAT's own ``--timeout``: its attacks before the search get a tenth of it, and at
#: 30 s or less it leaves out its restarts and MIP tightening (gurobipy's pip license is
#: size-limited). Its budget is :data:`ITERATIONS`; this one decides only on a machine so
#: slow that an instance would count as undecided.
SECONDS = 30
#: NeuralSAT's budget: branch-and-bound iterations (its ``max_iterations`` setting), after
#: which it answers ``early_stop``.
ITERATIONS = 500
#: Seconds before a NeuralSAT process counts as hung (it ran at most 40 s here).
HANG = 600


def neuralsat(onnx_path, vnnlib_path, folder: Path, timeout: int = SECONDS):
    """NeuralSAT on one instance with its ``--timeout`` ``timeout`` (s): ``(status, x,
    seconds)``, ``status`` its answer
    (``'sat'``, ``'unsat'``, ``'timeout'``, ``'early_stop'``, …), ``x`` the input of a
    ``sat`` answer (ndarray, ONNX input order) or None, ``seconds`` the wall time of the
    process. A process that writes no answer fails the test with its last output lines."""
    settings, result = folder / "neuralsat.json", folder / "neuralsat.txt"
    settings.write_text(json.dumps({"max_iterations": ITERATIONS}))
    command = [PYTHON, WORKER, "--net", onnx_path, "--spec", vnnlib_path, "--device", "cpu"]
    command += ["--verbosity", "0", "--timeout", str(timeout), "--setting_file", settings]
    command += ["--result_file", result, "--export_cex"]
    start = time.perf_counter()
    done = subprocess.run(
        [str(c) for c in command], capture_output=True, text=True, timeout=HANG, cwd=folder
    )
    seconds = time.perf_counter() - start
    tail = (done.stdout + done.stderr).strip().splitlines()[-15:]
    assert done.returncode == 0 and result.is_file(), (onnx_path, done.returncode, tail)
    status, x = read_answer(result)
    assert (status == "sat") == (x is not None), (onnx_path, status, x)
    return status, x, seconds


def assert_counterexample(model, hull, spec, x):
    """``x`` (a ``sat`` answer's box input) is a point of the hull whose float64 worst
    margin on ``model`` is ≤ 0, up to the re-check's tolerance
    (:func:`kpstudy.verify.export.check_counterexample`); returns that margin."""
    found = check_counterexample(model, hull, spec, x, "box")
    assert found["inside"] and found["violates"], (x, found)
    return found["margin"]


@pytest.mark.parametrize("form", ["compact", "full"])
def test_neuralsat_agrees_with_verify(tmp_path, form):
    """On 12 tiny keypoint-like proxies (tests/helpers/tiny_proxies.py; n = 1…4, box input
    form) NeuralSAT answers every instance (it loads them all), decides at least 10, each
    as ``verify`` decides it (both answers among them), every counterexample a real one."""
    rows = []
    for i in range(12):
        model, hull = make_instance(i)
        spec = model.spec
        start = time.perf_counter()
        ours = verify(model, hull, spec, timeout=600, max_nodes=1000)
        ours_time = time.perf_counter() - start
        folder = tmp_path / str(i)
        info = export_instance(folder, model, hull, spec, property_form=form)
        status, x, seconds = neuralsat(info["onnx"], info["vnnlib"], folder)
        rows.append((i, hull.n, ours.status, status, ours_time, seconds))
        if status in ("sat", "unsat") and ours.status != "unknown":
            assert {"sat": "violated", "unsat": "holds"}[status] == ours.status, rows[-1]
        if status == "sat":
            assert_counterexample(model, hull, spec, x)
    decided = [r for r in rows if r[3] in ("sat", "unsat") and r[2] != "unknown"]
    holds = sum(r[2] == "holds" for r in decided)
    print(
        f"\nNeuralSAT on {len(rows)} {form}-form instances: {len(decided)} decided by both "
        f"({holds} unsat/holds, {len(decided) - holds} sat/violated), all agreeing; "
        f"NeuralSAT {sum(r[5] for r in rows):.1f} s in all (max {max(r[5] for r in rows):.1f} "
        f"s, process start included), verify {sum(r[4] for r in rows):.2f} s (max "
        f"{max(r[4] for r in rows):.2f} s)"
    )
    assert len(decided) >= 10, rows
    assert holds >= 3 and len(decided) - holds >= 3, rows  # both answers are exercised


class CellPoolProxy(nn.Module):
    """Conv(1→2) → ReLU → channel 0 pooled by the proxy's cell pool (zeros padded
    asymmetrically along both axes: left 0, right 2, top 3, bottom 1, cells 5 × 3), then a
    ``Linear`` (identity weights) whose bias raises the keypoint's cell so that ``x0`` has
    margin ``seed_margin``. Input ``(B, 1, 6, 7)``, output ``(B, 6)``."""

    def __init__(self, x0: torch.Tensor, seed_margin: float = 0.05) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = nn.Conv2d(1, 2, 3, padding=1)
        self.pool, target = build_cell_pool((1, 4), (1, 2), (6, 7))
        cells = self.pool.n_v * self.pool.n_h
        self.spec = ArgmaxSpec([cells], [target])
        self.bias = nn.Linear(cells, cells)
        with torch.no_grad():
            self.bias.weight.copy_(torch.eye(cells))
            self.bias.bias.zero_()
            y0 = self(x0)[0]
            others = torch.cat([y0[:target], y0[target + 1 :]])
            self.bias.bias[target] = others.max() - y0[target] + seed_margin
        self.eval()

    def forward(self, x):
        return self.bias(self.pool(torch.relu(self.conv(x))[:, :1]).flatten(1))


def test_neuralsat_proves_through_the_cell_pool(tmp_path):
    """An instance that needs the proxy's cell pool (:class:`CellPoolProxy`, its zero
    padding exported as a one-hot depthwise ``Conv``: NeuralSAT's auto_LiRPA failed on the
    ``Pad`` it replaced) and that ``verify`` proves: NeuralSAT proves it too (``unsat``),
    so its bounds pass through the padding."""
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(1, 1, 6, 7, generator=g)
    model = CellPoolProxy(x0)
    assert model.pool.pad == (0, 2, 3, 1)
    hull = ConvexHull(
        x0 + 0.05 * torch.cat([torch.zeros_like(x0), torch.randn(2, *x0.shape[1:], generator=g)])
    )
    ours = verify(model, hull, model.spec, timeout=600, max_nodes=1000)
    info = export_instance(tmp_path, model, hull, model.spec)
    ops = [n.op_type for n in onnx.load(info["onnx"]).graph.node]
    assert "Pad" not in ops and "AveragePool" in ops
    # its initial bounds decide (0 iterations, ~10 s here): a long --timeout only keeps a
    # loaded machine from turning the proof into 'timeout'
    status, _, seconds = neuralsat(info["onnx"], info["vnnlib"], tmp_path, timeout=300)
    print(f"\nNeuralSAT through the cell pool: {status} in {seconds:.1f} s; verify {ours.status}")
    assert (ours.status, status) == ("holds", "unsat")


def test_neuralsat_reads_the_study_benchmark(study, tmp_path):
    """The tiny study's exported benchmark (the trained CNN's proxy: cell pooling with
    zero padding as a one-hot ``Conv``, ``AveragePool`` and ``Slice``, then the compact
    worst-margin tree; the ``study`` fixture of tests/conftest.py): NeuralSAT decides every
    instance as reference.csv (kpstudy's verdict) has it, and each counterexample is one for
    the proxy in float64."""
    from kpstudy.certify.allocation_method import build_instance
    from kpstudy.study.campaign import _context, grid, instance_vertices
    from kpstudy.study.vnncomp import export_benchmark, instance_name

    data, checkpoint = study
    instances = grid(data, "blocks", alphas=[1.0], kappas=[1.0], ms=[1], seeds=1)
    out = tmp_path / "bench"
    export_benchmark(checkpoint, data, out, instances, reference_nodes=40)
    with open(out / "reference.csv", newline="") as f:
        reference = {row["name"]: row["status"] for row in csv.DictReader(f)}
    backbone, seed_of = _context(str(checkpoint), str(data))
    for instance in instances:
        name = instance_name(instance)
        folder = tmp_path / name
        folder.mkdir()
        onnx_path, vnnlib_path = out / "onnx" / f"{name}.onnx", out / "vnnlib" / f"{name}.vnnlib"
        status, x, seconds = neuralsat(onnx_path, vnnlib_path, folder)
        print(f"\nNeuralSAT on {name}: {status} in {seconds:.1f} s; kpstudy {reference[name]}")
        assert {"sat": "violated", "unsat": "holds"}.get(status) == reference[name], status
        if status == "sat":
            vertices = instance_vertices(instance, data)
            built = build_instance(backbone, vertices, seed_of(instance.image_id))
            assert_counterexample(built.proxy, built.hull, built.spec, x)
