"""kpstudy.cli: a user's mistakes end in one line naming the argument, exit status 2 and
nothing written (never a traceback), for ``reproduce``'s arguments and every command's
inputs; Ctrl-C ends ``python -m kpstudy`` and ``python -m data_gen`` with status 130 and
one line."""

from __future__ import annotations

import io
import os
import select
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch

from tests.helpers.cli import assert_refused, run_cli

TINY_TRAIN = ["--epochs", "1", "--batch-size", "4", "--images", "8", "--threads", "1"]


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


#: Seconds the Ctrl-C test waits for the CLI's progress bar and then for its exit. They
#: only end a hung run: a busy machine takes seconds, so the verdict never depends on speed.
HANG = 600


def read_until(fd: int, mark: bytes | None, deadline: float) -> bytes:
    """What the pipe ``fd`` gives until ``mark`` is in it (``None``: until its end), read
    unbuffered (``communicate`` would lose what a buffered reader held back); fails at
    ``deadline`` (``time.monotonic``)."""
    got = b""
    while mark is None or mark not in got:
        if not select.select([fd], [], [], max(0.0, deadline - time.monotonic()))[0]:
            what = "end" if mark is None else repr(mark)
            pytest.fail(f"no {what} on the pipe within {HANG} s (a hang); so far {got!r}")
        chunk = os.read(fd, 65536)
        if not chunk:
            if mark is None:
                break
            pytest.fail(f"the CLI ended before its progress bar ({mark!r}) was drawn: {got!r}")
        got += chunk
    return got


def interrupt(module: str, *args) -> subprocess.CompletedProcess:
    """Run the CLI, wait on its stderr until its progress bar has drawn (``%|``: the work
    has begun; anything written before it, such as a first run's warning, is not the
    signal), then press Ctrl-C (SIGINT to its whole process group, as a terminal does)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", module, *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        bufsize=0,
        start_new_session=True,
        # as in a terminal: a shell's background job (CI started with `&`) ignores SIGINT,
        # and Python then installs no KeyboardInterrupt handler
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + HANG
    try:
        err = read_until(proc.stderr.fileno(), b"%|", deadline)
        os.killpg(proc.pid, signal.SIGINT)
        err += read_until(proc.stderr.fileno(), None, deadline)
        proc.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    return subprocess.CompletedProcess(proc.args, proc.returncode, None, err.decode())


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
    assert screen(proc.stderr)[-1] == line, proc.stderr


def screen(text: str) -> list[str]:
    """The lines a terminal shows for ``text``: ``\\r`` returns to column 0, what follows
    overwrites the line from there, ``\\n`` starts a new line; trailing blanks dropped."""
    lines = [[]]
    column = 0
    for char in text:
        if char == "\n":
            lines.append([])
            column = 0
        elif char == "\r":
            column = 0
        else:
            line = lines[-1]
            line[column : column + 1] = [char]
            column += 1
    shown = ["".join(line).rstrip() for line in lines]
    while shown and not shown[-1]:
        shown.pop()
    return shown


def test_screen_shows_what_a_terminal_shows():
    assert screen("bar  10%|#\rbar 100%|##\nok\n") == ["bar 100%|##", "ok"]
    assert screen("bar   0%|  | 0/4\rprog: stopped\n") == ["prog: stopped0/4"]


class Terminal(io.StringIO):
    """stderr as a file that raises ``KeyboardInterrupt`` (Ctrl-C) at the first write that
    ``ctrl_c(text)`` picks, after writing it when ``written``."""

    def __init__(self, ctrl_c=lambda text: False, written=True):
        super().__init__()
        self.ctrl_c, self.written = ctrl_c, written

    def write(self, text):
        if self.ctrl_c(text):
            self.ctrl_c = lambda text: False
            if self.written:
                super().write(text)
            raise KeyboardInterrupt
        return super().write(text)

    def isatty(self):
        return True


def first_state(text):
    return "%|" in text


@pytest.mark.parametrize(
    "moment, ctrl_c, written",
    [
        pytest.param("first state", first_state, True, id="while-the-bar-draws-its-first-state"),
        pytest.param("close", lambda text: text == "\n", False, id="in-close-before-its-line-end"),
        pytest.param("during the loop", lambda text: False, True, id="during-the-loop"),
    ],
)
def test_ctrl_c_starts_its_line_whenever_it_comes(monkeypatch, moment, ctrl_c, written):
    """Ctrl-C at any moment of a bar's life: the message is a line of its own (each moment
    made here, not raced for)."""
    from tqdm import tqdm

    from kpstudy.cli import interrupted

    stderr = Terminal(ctrl_c, written)
    monkeypatch.setattr(sys, "stderr", stderr)
    try:
        for _ in tqdm(range(3), desc="epoch 1/5"):
            if moment == "during the loop":
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        assert interrupted("prog") == 130
    shown = screen(stderr.getvalue())
    assert shown[-1] == "prog: interrupted", stderr.getvalue()
    assert all(line.startswith("epoch 1/5:") for line in shown[:-1]), stderr.getvalue()
    assert not getattr(tqdm, "_instances", ())


@pytest.mark.parametrize(
    "args, message",
    [
        (["--profile", "huge"], "profile: expected one of"),
        (["--images", "0"], "images: expected a positive number"),
        (["--seeds", "500"], "seeds: expected at most perturbed_seeds=8"),
        (["--stages", "data", "fly"], "stages: expected some of"),
        (["--retrain", "resnet18", "vgg"], "retrain: expected some of cnn_patch_smooth, resnet18"),
    ],
)
def test_bad_arguments_exit_non_zero_and_write_nothing(tmp_path, args, message):
    proc = subprocess.run(
        [sys.executable, "-m", "kpstudy", "reproduce", "--out", str(tmp_path), *args],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert message in proc.stderr and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert not any(tmp_path.iterdir())
