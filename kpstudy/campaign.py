"""Many verification instances: a grid, a resumable result store, a local pool or Dask.

An :class:`Instance` names one seed image's hull (perturbation kind, ``m`` images,
overlapping or not, or a brightness/contrast level) and the allocation's ``(α, κ)``.
:func:`run_campaign` certifies every instance of a grid that the :class:`ResultStore`
does not hold yet and writes each record the moment it arrives, in its own SQLite
transaction: a crash or Ctrl-C loses at most the instances still running, and a rerun
computes only what is missing. Instances run in the calling process (default,
``workers=1``), in ``workers`` local processes or on a Dask cluster
(``scheduler='tcp://…'``); each worker loads the checkpoint and the dataset once.
"""

from __future__ import annotations

import functools
import json
import os
import sqlite3
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from kpstudy.io import source_fingerprint

__all__ = ["Instance", "ResultStore", "Settings", "grid", "run_campaign", "store_path"]

GLOBAL_KINDS = ("brightness", "contrast")
LOCAL_KINDS = ("objects", "blocks")


@dataclass(frozen=True)
class Instance:
    """One verification instance of the study.

    ``m`` and ``overlapping`` are set for the local kinds (objects, blocks), ``level``
    (b or c) for the global kinds, whose hulls always have the seed and ±level.
    """

    kind: str
    image_id: int
    alpha: float
    kappa: float
    m: int | None = None
    overlapping: bool | None = None
    level: float | None = None

    @property
    def key(self) -> str:
        """A stable text key (the store's primary key)."""
        return json.dumps(asdict(self), sort_keys=True)


@dataclass(frozen=True)
class Settings:
    """What every instance of a campaign shares.

    Attributes
    ----------
    checkpoint : str
        A kpstudy checkpoint (``python -m kpstudy train``).
    data_dir : str
        The data_gen dataset with its perturbation sets.
    method, timeout :
        Bound method and seconds per instance for :func:`kpstudy.verify.verify`.
    check_samples : int
        Hull images through the target model for ``holds`` records.
    hull_seed : int
        Which ``m`` perturbed images make a local hull.
    pose_bound_timeout, pose_bound_stride, pose_bound_method :
        The pose-bound method beside the allocation method (:func:`kpstudy.certify.certify`):
        seconds per hull (``None`` skips it), cell side, bound method.
    """

    checkpoint: str
    data_dir: str
    method: str = "auto"
    timeout: float = 60.0
    check_samples: int = 200
    hull_seed: int = 0
    pose_bound_timeout: float | None = None
    pose_bound_stride: int = 1
    pose_bound_method: str = "forward"


def grid(
    data_dir,
    kind: str,
    *,
    alphas: Iterable[float],
    kappas: Iterable[float],
    ms: Iterable[int] = (2,),
    overlapping: Iterable[bool] = (False, True),
    levels: Iterable[float] | None = None,
    seeds: int | None = None,
) -> list[Instance]:
    """The instances of one perturbation kind over its seed images.

    Parameters
    ----------
    data_dir : path
        Dataset with ``perturbations/<kind>/`` (``python -m data_gen perturb``).
    kind : {'objects', 'blocks', 'brightness', 'contrast'}
    alphas, kappas : iterables of float > 0
    ms, overlapping : local kinds only
        Hull sizes and overlap classes; a seed image enters a cell only if it has ``m``
        perturbed images of that class.
    levels : global kinds only
        Brightness b or contrast c (default: every level of the set).
    seeds : int, optional
        Use the first ``seeds`` seed images (default all).
    """
    from data_gen.perturb import KINDS, load_perturbations

    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    alphas, kappas = _positive_list(alphas, "alphas"), _positive_list(kappas, "kappas")
    rows = load_perturbations(data_dir, kind)["images"]
    ids = sorted({r["image_id"] for r in rows})
    if seeds is not None:
        if isinstance(seeds, bool) or int(seeds) != seeds or seeds < 1:
            raise ValueError(f"seeds: expected a positive integer, got {seeds!r}")
        ids = ids[: int(seeds)]
    out = []
    if kind in GLOBAL_KINDS:
        stored = sorted({r["level"] for r in rows})
        levels = stored if levels is None else [float(v) for v in levels]
        missing = [v for v in levels if not any(np.isclose(v, s) for s in stored)]
        if missing:
            raise ValueError(f"levels: {missing} not in the {kind} set (it has {stored})")
        for image_id in ids:
            for level in levels:
                out += [Instance(kind, image_id, a, k, level=level) for a in alphas for k in kappas]
        return out
    ms = [int(m) for m in ms]
    count = {
        (i, o): sum(1 for r in rows if r["image_id"] == i and r["overlapping"] == o)
        for i in ids
        for o in (False, True)
    }
    most = max(count.values())
    if any(m < 1 or m > most for m in ms):
        raise ValueError(
            f"ms: expected hull sizes 1..{most} (the most perturbed {kind} images of one "
            f"class per seed image), got {ms}"
        )
    for image_id in ids:
        for o in overlapping:
            for m in ms:
                if count[image_id, bool(o)] >= m:
                    out += [
                        Instance(kind, image_id, a, k, m=m, overlapping=bool(o))
                        for a in alphas
                        for k in kappas
                    ]
    return out


class ResultStore:
    """Records keyed by :attr:`Instance.key` in one SQLite file (one transaction each)."""

    def __init__(self, path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("CREATE TABLE IF NOT EXISTS records (key TEXT PRIMARY KEY, record TEXT)")

    def _connect(self) -> sqlite3.Connection:
        try:
            return sqlite3.connect(self.path, timeout=60)
        except sqlite3.Error as exc:
            raise ValueError(f"store: cannot open {self.path} as SQLite ({exc})") from exc

    def keys(self) -> set[str]:
        with self._connect() as db:
            return {k for (k,) in db.execute("SELECT key FROM records")}

    def put(self, instance: Instance, record: dict) -> None:
        with self._connect() as db:  # commits on success, rolls back on error
            db.execute(
                "INSERT OR REPLACE INTO records VALUES (?, ?)",
                (instance.key, json.dumps(record)),
            )

    def frame(self, instances: Iterable[Instance] | None = None) -> pd.DataFrame:
        """One row per record: the instance's fields, then the record's (of ``instances``
        only, in their order, when given)."""
        with self._connect() as db:
            stored = dict(db.execute("SELECT key, record FROM records"))
        keys = list(stored) if instances is None else [i.key for i in instances if i.key in stored]
        rows = [{**json.loads(k), **json.loads(stored[k])} for k in keys]
        return pd.DataFrame(rows)


def store_path(folder, name: str, settings: Settings) -> Path:
    """``folder/<name>-<fingerprint>.sqlite``, the fingerprint hashing the checkpoint's
    bytes, the dataset's annotations and perturbation sets, the other settings and the
    code (:func:`kpstudy.io.source_fingerprint`): records of a retrained model, of other
    settings or of changed code never mix with these."""
    import hashlib

    _check_settings(settings)
    digest = hashlib.sha256()
    data = Path(settings.data_dir)
    for path in [
        Path(settings.checkpoint),
        data / "annotations.json",
        *sorted(data.glob("perturbations/*/meta.json")),
    ]:
        digest.update(path.read_bytes())
    rest = {k: v for k, v in asdict(settings).items() if k not in ("checkpoint", "data_dir")}
    digest.update(json.dumps(rest, sort_keys=True).encode())
    digest.update(source_fingerprint().encode())
    return Path(folder) / f"{name}-{digest.hexdigest()[:12]}.sqlite"


def run_campaign(
    instances: list[Instance],
    store,
    settings: Settings,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
    on_record: Callable[[Instance, dict], None] | None = None,
) -> pd.DataFrame:
    """Certify every instance the store lacks; return the records of ``instances``.

    Parameters
    ----------
    instances : list of Instance
    store : ResultStore or path
    settings : Settings
    workers : int
        Local worker processes (1: this process). Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:port``): the instances run there.
    progress : bool
        A progress bar with the time left.
    on_record : callable, optional
        Called with each new record after it is stored.
    """
    store = store if isinstance(store, ResultStore) else ResultStore(store)
    _check_settings(settings)
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    done = store.keys()
    missing = [i for i in dict.fromkeys(instances) if i.key not in done]
    bar = tqdm(total=len(missing), desc="instances", unit="inst", disable=not progress)

    def finish(instance, record):
        store.put(instance, record)
        bar.update()
        if on_record is not None:
            on_record(instance, record)

    try:
        if not missing:
            pass
        elif scheduler is not None:
            from distributed import Client
            from distributed import as_completed as dask_completed

            with Client(scheduler) as client:
                futures = {client.submit(run_instance, i, settings, pure=False): i for i in missing}
                for future in dask_completed(futures):
                    finish(futures[future], future.result())
        elif workers == 1:
            for instance in missing:
                finish(instance, run_instance(instance, settings))
        else:
            threads = max(1, (os.cpu_count() or 1) // int(workers))
            with ProcessPoolExecutor(
                int(workers),
                mp_context=get_context("spawn"),
                initializer=_init,
                initargs=(threads,),
            ) as pool:
                futures = {pool.submit(run_instance, i, settings): i for i in missing}
                for future in as_completed(futures):
                    finish(futures[future], future.result())
    finally:
        bar.close()
    return store.frame(instances)


def run_instance(instance: Instance, settings: Settings) -> dict:
    """Certify one instance (in whichever process runs it)."""
    from data_gen.perturb import hull_vertices, load_perturbations
    from kpstudy.certify import certify

    backbone, seed_of = _context(settings.checkpoint, settings.data_dir)
    vertices = hull_vertices(
        settings.data_dir,
        instance.image_id,
        instance.kind,
        instance.m,
        instance.overlapping,
        settings.hull_seed,
        level=instance.level,
    )
    record = certify(
        backbone,
        vertices,
        seed_of(instance.image_id),
        alpha=instance.alpha,
        kappa=instance.kappa,
        method=settings.method,
        timeout=settings.timeout,
        check_samples=settings.check_samples,
        pose_bound_timeout=settings.pose_bound_timeout,
        pose_bound_stride=settings.pose_bound_stride,
        pose_bound_method=settings.pose_bound_method,
    )
    clipped = 0.0
    if instance.kind in GLOBAL_KINDS:
        rows = load_perturbations(settings.data_dir, instance.kind)["images"]
        clipped = sum(
            r["clipped_fraction"]
            for r in rows
            if r["image_id"] == instance.image_id and np.isclose(r["level"], instance.level)
        )
    record["clipped_fraction"] = float(clipped)
    return record


@functools.lru_cache(maxsize=2)
def _context(checkpoint: str, data_dir: str):
    """The backbone and a seed-image lookup over the test split, loaded once per process."""
    from kpstudy.certify import SeedImage
    from kpstudy.data import load_keypoint_set
    from kpstudy.train import load_checkpoint

    backbone, _ = load_checkpoint(checkpoint)
    test = load_keypoint_set(data_dir, "test", backbone.input_size)
    index = {int(image_id): i for i, image_id in enumerate(test.image_ids)}

    def seed_of(image_id: int) -> SeedImage:
        return SeedImage.from_keypoint_set(test, index[image_id])

    return backbone, seed_of


def _init(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def _check_settings(settings: Settings) -> None:
    if not isinstance(settings, Settings):
        raise ValueError(f"settings: expected a Settings, got {type(settings).__name__}")
    if not Path(settings.checkpoint).is_file():
        raise FileNotFoundError(f"checkpoint: no file at {settings.checkpoint}")
    if not Path(settings.data_dir, "annotations.json").is_file():
        raise FileNotFoundError(f"data_dir: no data_gen dataset at {settings.data_dir}")
    from kpstudy.verify.bounds import METHODS

    if settings.method not in ("auto", *METHODS):
        raise ValueError(f"method: expected 'auto' or one of {METHODS}, got {settings.method!r}")
    if not settings.timeout > 0:
        raise ValueError(f"timeout: expected seconds > 0, got {settings.timeout}")
    if settings.pose_bound_timeout is not None and not settings.pose_bound_timeout > 0:
        raise ValueError(
            f"pose_bound_timeout: expected None or seconds > 0, got {settings.pose_bound_timeout}"
        )
    stride = settings.pose_bound_stride
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1 or stride % 2 == 0:
        raise ValueError(f"pose_bound_stride: expected an odd integer >= 1, got {stride!r}")
    from kpstudy.verify.reachable import METHODS as REGION_METHODS

    if settings.pose_bound_method not in REGION_METHODS:
        raise ValueError(
            f"pose_bound_method: expected one of {REGION_METHODS}, "
            f"got {settings.pose_bound_method!r}"
        )


def _positive_list(values, name: str) -> list[float]:
    out = [float(v) for v in values]
    if not out or any(not v > 0 for v in out):
        raise ValueError(f"{name}: expected one or more values > 0, got {out}")
    return out
