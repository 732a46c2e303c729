"""data_gen.dataset: annotation geometry, masks, COCO format, determinism, interruption."""

import gc
import multiprocessing
import multiprocessing.util
import os
import select
import signal
import threading
import time

import cv2
import numpy as np
import pytest
from pycocotools.coco import COCO

from data_gen import dataset as dataset_module
from data_gen.dataset import generate_dataset, load_coco, parse_size, read_image, split_of
from data_gen.keypoints import KEYPOINT_NAMES
from kpstudy.pose.geometry import project

SIZE = "240x150"

HANG = 300  # seconds: only a hang takes this long


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return generate_dataset(tmp_path_factory.mktemp("ds") / "data", 8, SIZE, seed=3, progress=False)


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*.png"))}


def _annotations(folder):
    coco = load_coco(folder)
    coco["info"].pop("date_created")
    return coco


def test_keypoints_reproject_and_visible_ones_lie_on_the_mask(small):
    coco = load_coco(small)
    P = np.asarray(coco["categories"][0]["keypoints_3d"])
    assert P.shape == (23, 3) and coco["categories"][0]["keypoints"] == list(KEYPOINT_NAMES)
    visible_total = 0
    for image, ann in zip(coco["images"], coco["annotations"]):
        K, R, t = np.asarray(image["K"]), np.asarray(ann["pose"]["R"]), np.asarray(ann["pose"]["t"])
        kp = np.reshape(ann["keypoints"], (-1, 3))
        np.testing.assert_allclose(kp[:, :2], project(P, R, t, K), atol=1e-3)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        mask = cv2.imread(str(small / image["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
        cols, rows = np.rint(kp[:, 0]).astype(int), np.rint(kp[:, 1]).astype(int)
        assert np.all(
            (kp[:, 2] >= 1) & (cols >= 0) & (cols < image["width"])
        )  # whole airplane in view
        # Visible keypoints lie on the mask, or within a pixel of it at thin edges (wing and
        # fin tips narrower than a pixel's centre spacing).
        visible = kp[:, 2] == 2
        near_mask = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert np.all(near_mask[rows[visible], cols[visible]])
        crown = [KEYPOINT_NAMES.index(n) for n in ("cockpit", "fuselage_front", "fuselage_mid")]
        assert np.all(kp[crown, 2] == 2) and np.all(mask[rows[crown], cols[crown]])
        visible_total += visible.sum()
        # The airplane spans 30–70 % of the frame (larger of width and height fractions).
        ys, xs = np.nonzero(mask)
        span = max((np.ptp(xs) + 1) / image["width"], (np.ptp(ys) + 1) / image["height"])
        assert 0.25 <= span <= 0.72
    assert visible_total >= 0.8 * 23 * len(coco["images"])  # seen from above, most are visible


def test_depth_matches_pose_and_intrinsics(small):
    coco = load_coco(small)
    image, ann = coco["images"][0], coco["annotations"][0]
    depth = (
        cv2.imread(str(small / image["depth_file"]), cv2.IMREAD_UNCHANGED)
        * coco["info"]["depth_scale_m"]
    )
    R, t = np.asarray(ann["pose"]["R"]), np.asarray(ann["pose"]["t"])
    P = np.asarray(coco["categories"][0]["keypoints_3d"])
    kp = np.reshape(ann["keypoints"], (-1, 3))
    z = (P @ R.T + t)[:, 2]
    mask = cv2.imread(str(small / image["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
    rows, cols = np.rint(kp[:, 1]).astype(int), np.rint(kp[:, 0]).astype(int)
    on_airplane = (kp[:, 2] == 2) & mask[rows, cols]
    assert on_airplane.sum() >= 8
    # Within a pixel's footprint on sloped surfaces (about 0.4 m per pixel here).
    np.testing.assert_allclose(depth[rows, cols][on_airplane], z[on_airplane], atol=0.5)
    hidden = kp[:, 2] == 1
    assert np.all(depth[rows, cols][hidden] < z[hidden] - 0.3)


def test_coco_loads_in_pycocotools(small):
    coco = COCO(str(small / "annotations.json"))
    ids = coco.getImgIds()
    assert len(ids) == 8 and len(coco.getAnnIds(imgIds=ids)) == 8
    ann = coco.loadAnns(coco.getAnnIds(imgIds=ids[0]))[0]
    mask = cv2.imread(str(small / coco.loadImgs(ids[0])[0]["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
    assert np.array_equal(coco.annToMask(ann).astype(bool), mask)
    assert ann["num_keypoints"] == sum(np.reshape(ann["keypoints"], (-1, 3))[:, 2] > 0)
    data = load_coco(small)
    assert {im["split"] for im in data["images"]} <= {"train", "val", "test"}
    assert sorted(sum(data["splits"].values(), [])) == list(range(8))


def test_splits_cover_every_image_once():
    names = split_of(1000, seed=5)
    assert names.count("train") == 800 and names.count("val") == 100 and names.count("test") == 100
    assert split_of(1000, seed=5) == names and split_of(1000, seed=6) != names


def test_same_seed_same_bytes_any_workers_other_seed_other_images(small, tmp_path):
    again = generate_dataset(tmp_path / "again", 8, SIZE, seed=3, workers=2, progress=False)
    assert _files(again) == _files(small)
    assert _annotations(again) == _annotations(small)
    other = generate_dataset(tmp_path / "other", 2, SIZE, seed=4, progress=False)
    first = read_image(other / "images/000000.png")
    assert not np.array_equal(first, read_image(small / "images/000000.png"))


def test_interrupted_run_leaves_no_output_and_resumes(small, tmp_path, monkeypatch):
    real = dataset_module._make
    calls = []

    def flaky(job):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(job)
        return real(job)

    monkeypatch.setattr(dataset_module, "_make", flaky)
    out = tmp_path / "data"
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(out, 8, SIZE, seed=3, progress=False)
    assert not out.exists()
    monkeypatch.setattr(dataset_module, "_make", real)
    generate_dataset(out, 8, SIZE, seed=3, progress=False)
    assert _files(out) == _files(small)
    assert not (tmp_path / ".data.partial").exists()


@pytest.fixture
def python_sigint():
    """Python's own SIGINT handler for the test, the previous one restored after: a shell's
    background job (CI started with `&`) starts with SIGINT ignored, and then Python
    installs none."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture
def sigint_elsewhere(python_sigint):
    """Another thread that takes SIGINT (as tqdm's monitor thread or OpenBLAS's do), and
    ``wait()``: returns once a SIGINT has reached this process's C-level handler (its
    byte on the set_wakeup_fd pipe), so that Python holds it pending. Restores the
    SIGINT handler and the wakeup fd afterwards."""
    if not hasattr(signal, "pthread_sigmask"):
        pytest.skip("no per-thread signal masks here")
    handler = signal.getsignal(signal.SIGINT)
    read, write = os.pipe()
    os.set_blocking(write, False)
    ready, stop = threading.Event(), threading.Event()

    def other():
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        ready.set()
        stop.wait()

    thread = threading.Thread(target=other, daemon=True)
    thread.start()
    ready.wait()
    previous_fd = signal.set_wakeup_fd(write)

    def wait():
        deadline = time.monotonic() + HANG
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                pytest.fail("the SIGINT never reached this process")
            if select.select([read], [], [], left)[0] and signal.SIGINT in os.read(read, 64):
                return

    try:
        yield wait
    finally:
        signal.set_wakeup_fd(previous_fd)
        signal.signal(signal.SIGINT, handler)
        stop.set()
        thread.join()
        os.close(read)
        os.close(write)


def _step(steps, step):
    steps.append(step)  # a Python call: a pending signal handler runs at it


def test_ctrl_c_while_held_surfaces_when_the_block_ends(sigint_elsewhere):
    steps = []
    with pytest.raises(KeyboardInterrupt):
        with dataset_module._sigint_held():
            os.kill(os.getpid(), signal.SIGINT)  # the kernel gives it to the other thread
            sigint_elsewhere()
            for step in range(5):
                _step(steps, step)
            _step(steps, "end")
    assert steps == [0, 1, 2, 3, 4, "end"]  # not interrupted inside the block
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())


def test_held_region_without_ctrl_c_and_off_the_main_thread(python_sigint):
    with dataset_module._sigint_held():
        pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    errors = []

    def held():
        try:
            with dataset_module._sigint_held():
                pass
        except BaseException as error:  # noqa: BLE001 - reported below
            errors.append(error)

    thread = threading.Thread(target=held)
    thread.start()
    thread.join()
    assert errors == []


def _gone(pid) -> bool:
    try:
        return os.waitpid(pid, os.WNOHANG)[0] != 0
    except ChildProcessError:  # already reaped (by its Popen)
        return True


def test_ctrl_c_while_the_pool_starts_leaves_no_worker_and_no_traceback(
    tmp_path, monkeypatch, capfd, sigint_elsewhere
):
    """Ctrl-C just after the first worker was spawned, before it was sent its task: the
    pool is still started whole, then torn down; no worker prints ``EOFError``."""
    real = multiprocessing.util.spawnv_passfds
    workers = []

    def spawn(path, args, passfds):
        pid = real(path, args, passfds)
        if any("spawn_main" in os.fsdecode(arg) for arg in args):
            workers.append(pid)
            if len(workers) == 1:
                os.kill(os.getpid(), signal.SIGINT)
                sigint_elsewhere()
        return pid

    monkeypatch.setattr(multiprocessing.util, "spawnv_passfds", spawn)
    out = tmp_path / "data"
    interrupted = False
    try:
        generate_dataset(out, 8, SIZE, seed=3, workers=2, progress=False)
    except KeyboardInterrupt:
        interrupted = True
    gc.collect()  # a half-made worker's Popen closes its pipe: the worker reads an EOF
    deadline = time.monotonic() + HANG
    while not all(_gone(pid) for pid in workers):
        if time.monotonic() > deadline:
            for pid in workers:
                if not _gone(pid):
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
            pytest.fail("a worker was left running")
        select.select([], [], [], 0.05)  # hang-only poll
    err = capfd.readouterr().err
    assert interrupted
    assert "Traceback" not in err and "Error" not in err, err
    assert len(workers) == 2  # the pool was started whole before the interrupt
    assert not multiprocessing.active_children()
    assert not out.exists()


def test_parse_size():
    assert parse_size("640x400") == (640, 400) and parse_size((1920, 1200)) == (1920, 1200)
    with pytest.raises(ValueError, match="size"):
        parse_size("x400")


def test_user_mesh_renders_like_a_built_in_variant(tmp_path):
    from data_gen.airplane import build_airplane, save_airplane

    mesh_path, json_path = save_airplane(build_airplane("swept"), tmp_path / "mine")
    out = generate_dataset(
        tmp_path / "user",
        2,
        "160x100",
        seed=0,
        mesh=mesh_path,
        keypoints_json=json_path,
        progress=False,
    )
    coco = load_coco(out)
    np.testing.assert_allclose(
        coco["categories"][0]["keypoints_3d"], build_airplane("swept").keypoints, atol=1e-9
    )
    builtin = generate_dataset(tmp_path / "builtin", 2, "160x100", 0, "swept", progress=False)
    for a, b in zip(coco["annotations"], load_coco(builtin)["annotations"]):
        np.testing.assert_allclose(a["keypoints"], b["keypoints"], atol=1e-6)
    with pytest.raises(FileNotFoundError, match="mesh_path"):
        generate_dataset(tmp_path / "x", 1, mesh=tmp_path / "no.ply", keypoints_json=json_path)
    assert not (tmp_path / "x").exists()
