"""``python -m kpstudy export-benchmark``: the study's instances in the VNN-COMP layout,
on the tiny study of tests/conftest.py (the ``study`` fixture)."""

from __future__ import annotations

import csv
import hashlib
import shutil
from types import SimpleNamespace

import numpy as np
import onnxruntime as ort
import pytest
import torch

from data_gen.perturb import hull_vertices
from kpstudy import __version__
from kpstudy.certify.allocation_method import build_instance
from kpstudy.cli import main
from kpstudy.study.campaign import _context, grid
from kpstudy.study.vnncomp import instance_name
from kpstudy.verify.export import read_vnnlib_polytope
from kpstudy.verify.simplex_map import box_of_lambda

BLOCKS = ["--kind", "blocks", "--ms", "1", "--seeds", "1", "--timeout", "30"]

BRIGHTNESS = ["--kind", "brightness", "--levels", "1", "--seeds", "1"]


def export(made, out, *args):
    """``python -m kpstudy export-benchmark`` in this process on ``made`` = (data, checkpoint)."""
    data, checkpoint = made
    return main(
        ["export-benchmark", "--checkpoint", str(checkpoint), "--data", str(data)]
        + ["--out", str(out), *args]
    )


def files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def bench(study, tmp_path_factory):
    """The blocks grid (box form, VNN-LIB 1.0, float32) exported once."""
    out = tmp_path_factory.mktemp("bench") / "blocks"
    assert export(study, out, *BLOCKS) == 0
    return out


def rows_of(out):
    with open(out / "instances.csv", newline="") as f:
        return list(csv.reader(f))


def test_layout_and_instances_csv(study, bench):
    data, checkpoint = study
    names = [
        instance_name(i) for i in grid(data, "blocks", alphas=[1.0], kappas=[1.0], ms=[1], seeds=1)
    ]
    assert len(names) == 2  # one seed image: a non-overlapping and an overlapping block
    assert files(bench) == sorted(
        ["README.md", "instances.csv"]
        + [f"onnx/{n}.onnx" for n in names]
        + [f"vnnlib/{n}.vnnlib" for n in names]
    )
    assert [p.name for p in bench.parent.iterdir()] == [bench.name]  # no staging left
    text = (bench / "instances.csv").read_text()
    assert text.endswith("\n") and "\r" not in text
    rows = rows_of(bench)
    assert rows == [[f"onnx/{n}.onnx", f"vnnlib/{n}.vnnlib", "30"] for n in names]
    readme = (bench / "README.md").read_text()
    digest = hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    assert digest in readme and f"kpstudy {__version__}" in readme
    assert "python -m kpstudy export-benchmark --checkpoint" in readme
    assert all(n in readme for n in names) and "target cell" in readme
    assert "property form `compact`" in readme and "one disjunct `Y_i ≤ 0`" in readme
    for n in names:  # the spec's comments name the instance's own ONNX file
        assert f"onnx/{n}.onnx" in (bench / "vnnlib" / f"{n}.vnnlib").read_text()


def test_onnx_equals_the_torch_proxy_on_hull_points(study, bench):
    """Each ONNX (onnxruntime, float32; the default compact form) gives each keypoint's
    least margin of the proxy's outputs at the hull's vertices and at Dirichlet samples,
    its input u mapped onto λ by the sorted spacings; the VNN-LIB file holds one disjunct
    per keypoint (23) in a few kilobytes, where the full form has one per competing cell
    (~4·10^4, ~2 MB)."""
    data, checkpoint = study
    backbone, seed_of = _context(str(checkpoint), str(data))
    for instance in grid(data, "blocks", alphas=[1.0], kappas=[1.0], ms=[1], seeds=1):
        name = instance_name(instance)
        vertices = hull_vertices(
            data, instance.image_id, "blocks", instance.m, instance.overlapping, 0
        )
        built = build_instance(backbone, vertices, seed_of(instance.image_id))
        hull, spec = built.hull, built.spec
        sess = ort.InferenceSession(
            str(bench / "onnx" / f"{name}.onnx"), providers=["CPUExecutionProvider"]
        )
        (inp,) = sess.get_inputs()
        assert (inp.name, inp.shape) == ("u", [1, hull.n])
        lam = torch.cat([torch.zeros(1, hull.n), torch.eye(hull.n)]).double()
        lam = torch.cat([lam, hull.sample(4, seed=3)])
        with torch.no_grad():
            cells = built.proxy(hull.image(lam))
        groups = sorted(set(spec.row_group.tolist()))  # the keypoints with competing cells
        want = spec.group_min(spec.margins(cells))[:, groups].numpy()
        scale = np.abs(cells.numpy()).max()
        for u, y in zip(box_of_lambda(lam), want):
            got = sess.run(["y"], {"u": u[None].float().numpy()})[0][0]
            np.testing.assert_allclose(got, y, rtol=1e-4, atol=1e-4 * scale)
        path = bench / "vnnlib" / f"{name}.vnnlib"
        poly = read_vnnlib_polytope(path)
        assert spec.n_groups == 23 and len(groups) <= 23 < spec.n_rows
        assert (poly["n_inputs"], poly["n_outputs"]) == (hull.n, len(groups))
        assert poly["disjuncts"] == [(None, i) for i in range(len(groups))]
        # measured: 2.2 kB; the full form of these instances: 38,691 disjuncts, 2.2 MB
        assert path.stat().st_size < 3000, (spec.n_rows, path.stat().st_size)


def test_build_instance_is_what_certify_verifies(study):
    """certify's record comes from build_instance's proxy, hull and spec."""
    from kpstudy.certify import certify
    from kpstudy.verify import verify

    data, checkpoint = study
    backbone, seed_of = _context(str(checkpoint), str(data))
    (image_id, *_) = sorted({i.image_id for i in grid(data, "blocks", alphas=[1], kappas=[1])})
    vertices = hull_vertices(data, image_id, "blocks", 2, True, 0)
    built = build_instance(backbone, vertices, seed_of(image_id), alpha=0.5)
    record = certify(
        backbone,
        vertices,
        seed_of(image_id),
        alpha=0.5,
        timeout=600,
        max_nodes=1000,
        check_samples=0,
    )
    assert record["cells"] == [c.tolist() for c in built.cells] and record["n"] == built.hull.n == 2
    assert built.spec is built.proxy.spec and built.inputs.shape == (3, 3, 64, 64)
    assert built.M.shape == (6, 46) and built.xi.shape == (6,) and built.R.shape == (3, 3)
    result = verify(built.proxy, built.hull, built.spec, timeout=600, max_nodes=1000)
    assert result.status == record["status"]
    assert list(result.group_status) == record["group_status"]


def test_rerun_gives_the_same_bytes(study, bench, tmp_path):
    """The same arguments write the same files, byte for byte (the first result moved
    aside, so that the command, --out included, is the same)."""
    first = tmp_path / "first"
    shutil.copytree(bench, first)
    # the README records the command, --out included: rerun into the very same path
    moved = bench.parent / "moved"
    bench.rename(moved)
    try:
        assert export(study, bench, *BLOCKS) == 0
        assert files(bench) == files(first)
        for name in files(first):
            assert (bench / name).read_bytes() == (first / name).read_bytes(), name
    finally:
        shutil.rmtree(bench)
        moved.rename(bench)


def test_vnnlib_2_simplex_full_form_parses(study, tmp_path):
    """VNN-LIB 2.0, the simplex input form and the full property form: the file parses,
    the ONNX takes λ and gives the proxy's cells, one output per cell."""
    vnnlib = pytest.importorskip("vnnlib")
    out = tmp_path / "bright"
    args = [*BRIGHTNESS, "--vnnlib-version", "2.0", "--input-form", "simplex"]
    assert export(study, out, *args, "--property-form", "full") == 0
    ((name, spec_file, timeout),) = rows_of(out)
    assert timeout == "60" and (out / name).is_file()
    query = vnnlib.parse_query_file(str(out / spec_file))
    ((x,),) = [net.inputs for net in query.networks]
    ((y,),) = [net.outputs for net in query.networks]
    assert x.dtype == vnnlib.DType.F32 and list(x.shape) == [1, 2]
    sess = ort.InferenceSession(str(out / name), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["lam"]
    (output,) = sess.get_outputs()
    assert list(y.shape) == output.shape and output.shape[1] > 23
    readme = (out / "README.md").read_text()
    assert "Σ λ ≤ 1" in readme and "property form `full`" in readme


def _refused(capsys, word, call):
    with pytest.raises(SystemExit) as exc:
        call()
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "export-benchmark" in lines[0] and word in lines[0], lines


def test_bad_input_is_refused_with_nothing_written(study, tmp_path, capsys):
    data, checkpoint = study
    out = tmp_path / "out"
    _refused(
        capsys,
        "checkpoint",
        lambda: main(
            ["export-benchmark", "--checkpoint", str(tmp_path / "none.pt"), "--data", str(data)]
            + ["--out", str(out), *BLOCKS]
        ),
    )
    _refused(
        capsys,
        "data",
        lambda: main(
            ["export-benchmark", "--checkpoint", str(checkpoint), "--data", str(tmp_path)]
            + ["--out", str(out), *BLOCKS]
        ),
    )
    bad_kind = ["--kind", "rain", "--seeds", "1"]
    _refused(capsys, "kind", lambda: export(study, out, *bad_kind))
    _refused(capsys, "input_form", lambda: export(study, out, *BLOCKS, "--input-form", "cube"))
    _refused(capsys, "dtype", lambda: export(study, out, *BLOCKS, "--dtype", "float16"))
    _refused(capsys, "property_form", lambda: export(study, out, *BLOCKS, "--property-form", "min"))
    _refused(
        capsys,
        "tolerance_units",
        lambda: export(study, out, *BLOCKS, "--tolerance-units", "pixels"),
    )
    _refused(
        capsys, "reference_nodes", lambda: export(study, out, *BLOCKS, "--reference-nodes", "0")
    )
    _refused(capsys, "mix", lambda: export(study, out, *BLOCKS, "--mix", "2"))  # no reference
    _refused(
        capsys,
        "mix",
        lambda: export(study, out, *BLOCKS, "--reference-nodes", "5", "--mix", "0"),
    )
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("hello")
    _refused(
        capsys,
        "checkpoint",
        lambda: main(
            ["export-benchmark", "--checkpoint", str(not_a_checkpoint), "--data", str(data)]
            + ["--out", str(out), *BLOCKS]
        ),
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.pt"]
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    _refused(capsys, "out", lambda: export(study, full, *BLOCKS))
    assert files(full) == ["keep.txt"]
    _refused(capsys, "out", lambda: export(study, full / "keep.txt", *BLOCKS))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "notes.pt"]


@pytest.mark.parametrize(
    "option, message",
    [
        (dict(timeout=0), "timeout: expected seconds > 0, got 0"),
        (dict(timeout=True), "timeout: expected seconds > 0, got True"),
        (dict(timeout=float("inf")), "timeout: expected finite seconds > 0, got inf"),
        (dict(input_form="cube"), "input_form: expected one of box, simplex, got 'cube'"),
        (dict(vnnlib_version="3.0"), "vnnlib_version: expected one of 1.0, 2.0, got '3.0'"),
        (dict(dtype="float16"), "dtype: expected one of float32, float64, got 'float16'"),
        (
            dict(tolerance_units="pixels"),
            "tolerance_units: expected one of heatmap, paper, got 'pixels'",
        ),
    ],
)
def test_the_export_options_are_checked_before_anything_is_read(tmp_path, option, message):
    from kpstudy.study.vnncomp import export_benchmark

    checkpoint, data = tmp_path / "model.pt", tmp_path / "data"
    checkpoint.write_text("not read")
    data.mkdir()
    (data / "annotations.json").write_text("not read")
    with pytest.raises(ValueError) as refused:
        export_benchmark(checkpoint, data, tmp_path / "out", [], **option)
    assert str(refused.value) == message
    assert not (tmp_path / "out").exists()


def test_seeds_that_cannot_be_certified_are_left_out(study, tmp_path, monkeypatch):
    """A seed build_instance refuses is listed in README.md; a grid of only such seeds is
    refused, naming ``instances``, with nothing left behind."""
    import kpstudy.certify.allocation_method
    from kpstudy.study.vnncomp import export_benchmark

    data, checkpoint = study
    instances = grid(data, "blocks", alphas=[1.0], kappas=[1.0], ms=[1], seeds=1)
    real = kpstudy.certify.allocation_method.build_instance

    def refuse_overlapping(backbone, vertices, seed, **kw):
        if (
            vertices[1].tobytes()
            == hull_vertices(data, seed.image_id, "blocks", 1, True)[1].tobytes()
        ):
            raise ValueError("seed: keypoint 3 lies outside the heatmap (test)")
        return real(backbone, vertices, seed, **kw)

    monkeypatch.setattr(kpstudy.certify.allocation_method, "build_instance", refuse_overlapping)
    done = export_benchmark(checkpoint, data, tmp_path / "some", instances)
    ((name, reason),) = done["skipped"]
    assert name.endswith("_ov_a1_k1") and done["written"] == [instance_name(instances[0])]
    readme = (tmp_path / "some" / "README.md").read_text()
    assert "## Left out" in readme and reason in readme
    assert len(rows_of(tmp_path / "some")) == 1

    def refuse(*args, **kw):
        raise ValueError("seed: PnP gives no valid pose (test)")

    monkeypatch.setattr(kpstudy.certify.allocation_method, "build_instance", refuse)
    with pytest.raises(ValueError, match="^instances: no seed image"):
        export_benchmark(checkpoint, data, tmp_path / "none", instances)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["some"]


def reference_rows(out):
    with open(out / "reference.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_reference_csv_holds_kpstudys_verdicts(study, tmp_path):
    """``--reference-nodes``: reference.csv has a row per instance of instances.csv, in its
    order, with the status and node count that :func:`kpstudy.verify.verify` gives the
    instance's proxy, hull and spec under that node budget (and no time budget), the
    method and the budget; README.md reports them."""
    import math

    from kpstudy.verify import verify

    data, checkpoint = study
    out = tmp_path / "ref"
    assert export(study, out, *BLOCKS, "--reference-nodes", "40") == 0
    rows = reference_rows(out)
    assert [f"onnx/{r['name']}.onnx" for r in rows] == [row[0] for row in rows_of(out)]
    backbone, seed_of = _context(str(checkpoint), str(data))
    for instance, row in zip(grid(data, "blocks", alphas=[1], kappas=[1], ms=[1], seeds=1), rows):
        assert row["name"] == instance_name(instance)
        vertices = hull_vertices(
            data, instance.image_id, "blocks", instance.m, instance.overlapping, 0
        )
        built = build_instance(backbone, vertices, seed_of(instance.image_id))
        ours = verify(built.proxy, built.hull, built.spec, timeout=math.inf, max_nodes=40)
        assert (row["status"], int(row["nodes"])) == (ours.status, ours.nodes)
        assert (row["method"], row["max_nodes"]) == ("auto", "40")
        assert float(row["time"]) >= 0
    readme = (out / "README.md").read_text()
    assert "## Reference verdicts" in readme and "a budget of 40 branch-and-bound" in readme
    assert "| kpstudy | nodes |" in readme
    assert not (tmp_path / "plain").exists()
    assert export(study, tmp_path / "plain", *BLOCKS) == 0  # off by default
    assert not (tmp_path / "plain" / "reference.csv").exists()


def test_the_tolerance_reading_reaches_the_instances(study, tmp_path):
    """``--tolerance-units paper`` exports the paper reading's cells, larger than the
    heatmap reading's: each VNN-LIB file's header states the proxy's cells per keypoint,
    those of :func:`kpstudy.certify.build_instance` under that reading, and the paper's
    are fewer."""
    import re

    data, checkpoint = study
    backbone, seed_of = _context(str(checkpoint), str(data))
    (instance,) = grid(data, "brightness", alphas=[3], kappas=[1], levels=[1], seeds=1)
    vertices = hull_vertices(data, instance.image_id, "brightness", level=1.0)
    cells = {}
    for units in ("heatmap", "paper"):
        out = tmp_path / units
        args = ["--kind", "brightness", "--levels", "1", "--seeds", "1", "--alphas", "3"]
        assert export(study, out, *args, "--tolerance-units", units) == 0
        ((_, spec_file, _),) = rows_of(out)
        header = re.search(
            r"model outputs: (\d+) in 23 groups \[([\d, ]+)\]", (out / spec_file).read_text()
        )
        built = build_instance(
            backbone, vertices, seed_of(instance.image_id), alpha=3, tolerance_units=units
        )
        sizes = [int(v) for v in header[2].split(",")]
        assert sizes == built.spec.group_sizes and int(header[1]) == built.spec.n_outputs
        assert f"tolerance reading `{units}`" in (out / "README.md").read_text()
        cells[units] = sizes
    assert sum(cells["paper"]) < sum(cells["heatmap"])  # measured: 4,689 against 13,014
    assert all(p <= h for p, h in zip(cells["paper"], cells["heatmap"]))


def test_mix_keeps_instances_until_each_verdict_is_represented(study, tmp_path, monkeypatch):
    """``mix=1`` walks the grid in order: it keeps the first instance of each verdict,
    leaves out one whose class is full and stops when every class has one, never building
    the rest; reference.csv and README.md say which and why. (The tiny study's CNN
    violates every instance, so kpstudy's verify answers from a script here.)"""
    import kpstudy.verify
    from kpstudy.study.vnncomp import export_benchmark

    data, checkpoint = study
    instances = grid(data, "blocks", alphas=[1, 2], kappas=[1], ms=[1, 2], seeds=2)
    assert len(instances) == 16
    answers = iter(["violated", "violated", "holds", "unknown", "holds"])

    def scripted(model, input_set, spec, **kw):
        assert kw["max_nodes"] == 7 and kw["timeout"] == float("inf")
        return SimpleNamespace(status=next(answers), time=0.5, nodes=3)

    monkeypatch.setattr(kpstudy.verify, "verify", scripted)
    names = [instance_name(i) for i in instances]
    done = export_benchmark(checkpoint, data, tmp_path / "mix", instances, reference_nodes=7, mix=1)
    assert done["written"] == [names[0], names[2], names[3]]
    assert done["unmixed"] == [(names[1], "violated")] and done["unexamined"] == 12
    rows = reference_rows(tmp_path / "mix")
    assert [(r["name"], r["status"]) for r in rows] == [
        (names[0], "violated"),
        (names[2], "holds"),
        (names[3], "unknown"),
    ]
    readme = (tmp_path / "mix" / "README.md").read_text()
    assert "Selection (`mix` = 1)" in readme and "the grid's last 12 were never built" in readme
    assert f"- {names[1]}: violated" in readme.split("## Not kept by the mix")[1]
    assert "Counts: 1 holds, 1 violated, 1 unknown." in readme
