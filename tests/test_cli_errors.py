"""A user's mistakes end in one line naming the argument, exit status 2 and nothing
written (never a traceback); Ctrl-C ends with status 130 and one line; the notebooks'
kernels run over IPC, so ``make reproduce`` prints no IPKernel eavesdropping warning."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys

import pytest
import torch

from data_gen.keypoints import KEYPOINT_NAMES

TINY_TRAIN = ["--epochs", "1", "--batch-size", "4", "--images", "8", "--threads", "1"]


def run_cli(module: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True
    )


def assert_refused(proc: subprocess.CompletedProcess, *words: str) -> None:
    """Exit 2, no traceback, one line on stderr naming ``words``."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    for word in words:
        assert word in lines[0], lines[0]


@pytest.fixture
def read_only(tmp_path):
    """An empty folder this process cannot write into (mode 0555; for root, whom modes do
    not stop, also the immutable attribute)."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    immutable = False
    if os.access(folder, os.W_OK):
        immutable = shutil.which("chattr") is not None and (
            subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0
        )
        if not immutable:
            folder.chmod(0o755)
            pytest.skip("no way to make a folder read-only for this user")
    yield folder
    if immutable:
        subprocess.run(["chattr", "-i", str(folder)], check=True)
    folder.chmod(0o755)


@pytest.fixture(scope="module")
def checkpoint(tiny_dataset, tmp_path_factory):
    from kpstudy.models.training import TrainConfig, train

    path = tmp_path_factory.mktemp("ckpt") / "cnn.pt"
    train(tiny_dataset, path, TrainConfig(epochs=1, batch_size=4, images=8, seed=1), progress=False)
    return path


def test_train_out_in_a_read_only_place_is_refused_before_training(tiny_dataset, read_only):
    proc = run_cli(
        "kpstudy", "train", "--data", tiny_dataset, "--out", read_only / "cnn.pt", *TINY_TRAIN
    )
    assert_refused(proc, "out:", "read-only")
    assert not any(read_only.iterdir())


def test_evaluate_out_in_a_read_only_place_is_refused(tiny_dataset, checkpoint, read_only):
    proc = run_cli(
        "kpstudy",
        "evaluate",
        "--checkpoint",
        checkpoint,
        "--data",
        tiny_dataset,
        "--out",
        read_only / "metrics",
    )
    assert_refused(proc, "out:", "read-only")
    assert not any(read_only.iterdir())


def test_reproduce_out_in_a_read_only_place_is_refused(read_only):
    proc = run_cli("kpstudy", "reproduce", "--out", read_only / "results", "--stages", "report")
    assert_refused(proc, "out:", "read-only")
    assert not any(read_only.iterdir())


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_train_on_cuda_without_cuda_is_refused(tiny_dataset, tmp_path):
    out = tmp_path / "out"
    proc = run_cli(
        "kpstudy",
        "train",
        "--data",
        tiny_dataset,
        "--out",
        out / "cnn.pt",
        "--device",
        "cuda",
        *TINY_TRAIN,
    )
    assert_refused(proc, "device:", "'cuda'")
    assert not out.exists()


def test_a_flat_single_triangle_mesh_is_refused_before_any_output(tmp_path):
    mesh = tmp_path / "triangle.obj"
    mesh.write_text("v -20 -20 0\nv 20 -20 0\nv 0 20 0\nf 1 2 3\n")
    # 23 distinct keypoints on the triangle: only the mesh is wrong
    keypoints = [
        {"name": name, "xyz": [-8 + 4 * (i % 5), -10 + 3 * (i // 5), 0]}
        for i, name in enumerate(KEYPOINT_NAMES)
    ]
    (tmp_path / "keypoints.json").write_text(json.dumps({"keypoints": keypoints}))
    work = tmp_path / "work"
    work.mkdir()
    proc = run_cli(
        "data_gen",
        "dataset",
        "--out",
        work / "o_mesh2",
        "--n",
        "2",
        "--size",
        "160x100",
        "--mesh",
        mesh,
        "--keypoints",
        tmp_path / "keypoints.json",
    )
    assert_refused(proc, "mesh_path:", "three dimensions")
    assert not any(work.iterdir())  # no .o_mesh2.partial/


def test_a_negative_seed_is_refused_before_any_output(tmp_path):
    proc = run_cli("data_gen", "dataset", "--out", tmp_path / "data", "--n", "2", "--seed", "-1")
    assert_refused(proc, "seed:", "non-negative")
    assert not any(tmp_path.iterdir())  # no .data.partial/


@pytest.mark.parametrize(
    "command", [["kpstudy", "train"], ["data_gen", "perturb", "--kind", "blocks"]]
)
def test_a_corrupt_coco_file_is_named(tmp_path, command):
    data = tmp_path / "data"
    data.mkdir()
    annotations = data / "annotations.json"
    annotations.write_text('{"images": [{"id": 0, "file_')  # truncated
    module, *args = command
    if module == "kpstudy":
        args += ["--out", tmp_path / "cnn.pt"]
    proc = run_cli(module, *args, "--data", data)
    assert_refused(proc, "data_dir:", str(annotations), "not valid JSON")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["annotations.json", "data"]


def test_verify_refuses_a_hull_of_another_dtype_than_the_model():
    from kpstudy.verify import ArgmaxSpec, ConvexHull, verify
    from tests.verify_nets import MixedNet, hull_vertices

    net = MixedNet(0).eval()  # float32
    hull = ConvexHull(hull_vertices(0, 3, (2, 8, 8), dtype=torch.float64))
    with pytest.raises(ValueError, match=r"input_set: expected images of the model's dtype"):
        verify(net, hull, ArgmaxSpec([3, 3], [0, 0]), timeout=5)


def interrupt(module: str, *args) -> subprocess.CompletedProcess:
    """Run the CLI, press Ctrl-C (SIGINT to its whole process group, as a terminal does)
    once its progress bar is on stderr (the work has begun; anything written before it,
    such as a first run's warning, is not the signal)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", module, *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        # as in a terminal: a shell's background job (CI started with `&`) ignores SIGINT,
        # and Python then installs no KeyboardInterrupt handler
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        first = b""
        while b"%|" not in first and proc.poll() is None:
            first += proc.stderr.read(1)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, (first + err).decode())


@pytest.mark.parametrize(
    "module, args, line",
    [
        ("kpstudy", ["train", "--epochs", "500", "--batch-size", "4"], "kpstudy: interrupted"),
        (
            "data_gen",
            ["dataset", "--n", "200", "--size", "160x100", "--workers", "2"],
            "data_gen dataset: interrupted",
        ),
    ],
)
def test_ctrl_c_exits_130_with_one_line(tiny_dataset, tmp_path, module, args, line):
    if module == "kpstudy":
        args = [*args, "--data", tiny_dataset, "--out", tmp_path / "cnn.pt"]
    else:
        args = [*args, "--out", tmp_path / "data"]
    proc = interrupt(module, *args)
    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.splitlines()[-1] == line


def test_notebook_kernels_run_over_ipc_without_the_tcp_warning(tmp_path, capfd):
    import nbformat
    import papermill

    from kpstudy.study.reproduction import _ipc_kernel

    notebook = nbformat.v4.new_notebook()
    notebook.cells = [nbformat.v4.new_code_cell("x = 1"), nbformat.v4.new_code_cell("x * 2")]
    notebook.cells[0].metadata["tags"] = ["parameters"]
    notebook.metadata["kernelspec"] = {"name": "python3", "language": "python"}
    nbformat.write(notebook, tmp_path / "tiny.ipynb")
    sockets = tmp_path / "sockets"
    sockets.mkdir()
    papermill.execute_notebook(
        str(tmp_path / "tiny.ipynb"),
        str(tmp_path / "out.ipynb"),
        parameters={"x": 21},
        cwd=str(tmp_path),
        progress_bar=False,
        kernel_name="python3",
        config=_ipc_kernel(str(sockets)),
    )
    assert "eavesdropping" not in capfd.readouterr().err  # the kernel's own stderr too
    result = nbformat.read(tmp_path / "out.ipynb", as_version=4).cells[-1].outputs
    assert result[0]["data"]["text/plain"] == "42"
    assert not any(sockets.iterdir())  # the kernel's sockets are gone with it
    assert not list(tmp_path.glob("kernel-*"))
