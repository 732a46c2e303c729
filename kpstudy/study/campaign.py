"""Many verification instances: a grid, a resumable result store, a local pool or Dask.

An :class:`Instance` names one seed image's hull (perturbation kind, ``m`` images,
overlapping or not, or a brightness/contrast level) and the allocation's ``(α, κ)``.
:func:`run_campaign` certifies every instance of a grid that the :class:`ResultStore`
does not hold yet and writes each record the moment it arrives, in its own SQLite
transaction: a crash or Ctrl-C loses at most the instances still running, and a rerun
computes only what is missing. Instances run in the calling process (default,
``workers=1``), in ``workers`` local processes or on a Dask cluster
(``scheduler='tcp://…'``); each worker loads the checkpoint and the dataset once.

Reliability:

* The checkpoint, the dataset (its annotations and test images) and the perturbation
  sets the instances use are loaded and checked once, before the store is opened: one
  that cannot be read is refused with a one-line ``ValueError`` naming the file, and
  nothing is written (not an ``'error'`` record per instance).
* A store records what made it (:func:`provenance`: the checkpoint's bytes, the dataset's
  annotations and perturbation sets, the other settings, the code) and refuses, with a
  one-line ``ValueError`` naming ``store``, a campaign of another provenance: records of
  another model, dataset, settings or code never mix. The file is created with the first
  record, so that refused arguments leave nothing behind.
* One store, one running campaign: a campaign holds an exclusive lock on its store
  (``_StoreLock``, ``fcntl.flock`` on ``<store>.lock``) while it runs, and a second
  one on the same store is refused with a one-line ``ValueError`` naming ``store``. The
  operating system drops the lock of a process that dies, even by SIGKILL, so a killed
  campaign's store resumes at once.
* An instance that raises (a seed that cannot be certified, …) is stored with status
  ``'error'`` and its message; the campaign goes on. The command line lists such
  instances and exits with status 1 (:class:`InstanceErrors`).
* Local worker processes die with the campaign: they exit when their parent does
  (``PR_SET_PDEATHSIG`` on Linux, and a thread watching the parent's pid), and SIGTERM
  to the campaign's process stops them before it exits (status 143).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import signal
import socket
import sqlite3
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, fields
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from kpstudy import _checks
from kpstudy.io import check_output_file, source_fingerprint

__all__ = [
    "Instance",
    "InstanceErrors",
    "ResultStore",
    "Settings",
    "grid",
    "provenance",
    "run_campaign",
    "run_study",
    "store_path",
]

GLOBAL_KINDS = ("brightness", "contrast")
LOCAL_KINDS = ("objects", "blocks")


class InstanceErrors(Exception):
    """Some instances of a run ended with status ``'error'`` (their records are stored).
    The command line (``campaign``, ``reproduce``) ends with its message, one line with the
    count, and exit status 1."""


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


def _setting(default, help: str):
    """A :class:`Settings` field and its command-line help (``python -m kpstudy campaign``
    offers every field that has one)."""
    return field(default=default, metadata={"help": help})


#: The :class:`Settings` fields of the allocation method (also those a model's own
#: allocation budget may set, :func:`run_study`) → its
#: :class:`~kpstudy.certify.allocation_method.AllocationOptions` field.
ALLOCATION_SETTINGS = {"method": "method", "nodes": "max_nodes", "timeout": "timeout"}


def allocation_options(prefix: str = "", **chosen):
    """The allocation method's :class:`~kpstudy.certify.allocation_method.AllocationOptions`
    of :data:`ALLOCATION_SETTINGS` ``chosen`` (one left out: its default), checked: a
    ``ValueError`` names the setting, after ``prefix``."""
    from kpstudy.certify.allocation_method import AllocationOptions

    with _checks.named({v: k for k, v in ALLOCATION_SETTINGS.items()}, prefix):
        return AllocationOptions(**{ALLOCATION_SETTINGS[k]: v for k, v in chosen.items()})


@dataclass(frozen=True)
class Settings:
    """What every instance of a campaign shares: the one declaration of the campaign
    settings, from which the command line (``add_arguments()``), the notebooks and the
    profiles (their keywords) build a campaign.

    Attributes
    ----------
    checkpoint : str
        A kpstudy checkpoint (``python -m kpstudy train``).
    data_dir : str
        The data_gen dataset with its perturbation sets.
    method, timeout, nodes :
        Bound method, seconds and node budget (``None``: the seconds alone decide) per
        instance for :func:`kpstudy.verify.bab.verify`.
    check_samples : int
        Hull images through the target model for ``holds`` records.
    hull_seed : int
        Which ``m`` perturbed images make a local hull.
    pose_bound_timeout, pose_bound_stride, pose_bound_method :
        The pose-bound method beside the allocation method (:func:`kpstudy.certify.hull.certify`):
        seconds per hull (``None`` skips it), cell side, bound method.
    pose_bound_nodes, pose_bound_start_depth, pose_bound_start_splits :
        Its node budget per hull (``None``: the seconds alone decide; with a budget the
        seconds only cap a slow machine; 0: the witnesses alone) and the hull's splits
        before the first bounds: ``start_depth + ⌈start_splits · m⌉`` for a hull of ``m``
        perturbed images.
    pose_bound_refine_nodes :
        Its focused second search (0: none).
    tolerance_units : {'heatmap', 'paper'}
        How the allocation method reads its tolerances
        (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`); the pose-bound method has none.
    """

    checkpoint: str
    data_dir: str
    method: str = _setting("auto", "auto (zonotope), ibp, forward, crown or zonotope")
    timeout: float = _setting(60.0, "seconds per instance")
    nodes: int | None = _setting(
        None,
        "node budget per instance of the allocation method (the same verdicts on any "
        "machine; the seconds then only cap a slow one)",
    )
    check_samples: int = _setting(200, "hull images through the target model per 'holds'")
    hull_seed: int = _setting(0, "which perturbed images make a local hull")
    pose_bound_timeout: float | None = _setting(
        None, "also run the pose-bound method, this many seconds per hull"
    )
    pose_bound_stride: int = _setting(1, "the pose-bound method's odd cell side (1: argmax)")
    pose_bound_method: str = _setting(
        "forward", "bounds of the pose-bound method's regions: forward, zonotope or ibp"
    )
    pose_bound_nodes: int | None = _setting(
        None, "node budget of the pose-bound method per hull (the same verdicts on any machine)"
    )
    pose_bound_start_depth: int = _setting(
        0, "splits of each hull before the pose-bound method's first bounds"
    )
    pose_bound_start_splits: float = _setting(
        0.0,
        "more splits of each hull before the pose-bound method's first bounds, per "
        "perturbed image of the hull (rounded up)",
    )
    pose_bound_refine_nodes: int = _setting(
        0,
        "nodes of focused second pose-bound searches for an unknown verdict, split only "
        "where a pixel that keeps it open has no witness (0: none)",
    )
    tolerance_units: str = _setting(
        "heatmap",
        "the allocation's reading: heatmap pixels (sound) or the paper's (allocated per "
        "image pixel, used as heatmap pixels)",
    )

    def allocation_options(self):
        """The allocation method's options (:func:`allocation_options`), checked."""
        return allocation_options(**{name: getattr(self, name) for name in ALLOCATION_SETTINGS})

    def pose_bound_options(self):
        """The pose-bound method's options of the ``pose_bound_*`` fields, checked
        (:func:`kpstudy.certify.hull.pose_bound_options`: ``None`` when
        ``pose_bound_timeout`` is ``None``)."""
        from kpstudy.certify.hull import POSE_BOUND_KEYWORDS, pose_bound_options

        return pose_bound_options(**{name: getattr(self, name) for name in POSE_BOUND_KEYWORDS})

    def certify_options(self) -> dict:
        """The keywords of :func:`kpstudy.certify.hull.certify_cells` these settings give."""
        options = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in ("checkpoint", "data_dir", "hull_seed"):
            del options[name]
        options["max_nodes"] = options.pop("nodes")
        return options

    @classmethod
    def from_arguments(cls, args) -> Settings:
        """The settings of parsed ``add_arguments()`` options (``args.checkpoint``,
        ``args.data``)."""
        chosen = {f.name: getattr(args, f.name) for f in fields(cls) if "help" in f.metadata}
        return cls(str(args.checkpoint), str(args.data), **chosen)


def add_arguments(parser, cls=Settings, group: str | None = None) -> None:
    """An ``argparse`` option per field with help of the dataclass ``cls`` (its metadata's
    ``'help'``; :class:`Settings`, :class:`kpstudy.models.training.TrainConfig`):
    ``--pose-bound-nodes`` for ``pose_bound_nodes``, typed as the field and with its
    default. Only the fields whose metadata's ``'group'`` is ``group`` (default: those of
    no group), so that a caller can put a group's in an argument group of its own."""
    for f in fields(cls):
        if "help" not in f.metadata or f.metadata.get("group") != group:
            continue
        kind = float if "float" in f.type else int if "int" in f.type else str
        default = "" if f.default is None else f" (default {f.default})"
        parser.add_argument(
            "--" + f.name.replace("_", "-"),
            type=kind,
            default=f.default,
            help=f.metadata["help"] + default,
        )


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

    _checks.choice(kind, "kind", KINDS)
    alphas, kappas = _positive_list(alphas, "alphas"), _positive_list(kappas, "kappas")
    rows = load_perturbations(data_dir, kind)["images"]
    ids = sorted({r["image_id"] for r in rows})
    if seeds is not None:
        ids = ids[: _checks.integer(seeds, "seeds", minimum=1)]
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
    """Records keyed by :attr:`Instance.key` in one SQLite file (one transaction each),
    with the :func:`provenance` of the campaign that made them.

    Parameters
    ----------
    path : path
        The SQLite file. A missing file is created with the first :meth:`put` (its
        folders too); until then nothing is written.
    provenance : dict, optional
        What makes this campaign's records (:func:`provenance`). Given, an existing store
        made by another provenance, or holding records of unknown provenance, is refused
        (``ValueError`` naming ``store``), as is a path that is not a SQLite store; one
        that cannot be created raises :func:`kpstudy.io.check_output_file`'s ``OSError``.
        ``None`` opens the store read-only (:meth:`keys`, :meth:`frame`), whatever made it.
    """

    def __init__(self, path, provenance: dict | None = None) -> None:
        self.path = Path(path)
        self.provenance = provenance
        if self.path.exists():
            self._check_existing()
        elif provenance is not None:
            check_output_file(self.path, "store")

    @contextlib.contextmanager
    def _db(self, readonly: bool = False):
        """A connection (read-only: never creates the file), committed on success, rolled
        back on error, closed in any case."""
        try:
            if readonly:
                uri = Path(os.path.abspath(self.path)).as_uri() + "?mode=ro"
                db = sqlite3.connect(uri, uri=True, timeout=60)
            else:
                db = sqlite3.connect(self.path, timeout=60)
        except sqlite3.Error as exc:
            raise ValueError(f"store: cannot open {self.path} as SQLite ({exc})") from exc
        try:
            with db:
                yield db
        except sqlite3.DatabaseError as exc:
            raise ValueError(f"store: {self.path} is not a usable SQLite store ({exc})") from exc
        finally:
            db.close()

    def _check_existing(self) -> None:
        if self.path.is_dir():
            raise ValueError(f"store: {self.path} is a directory, expected a SQLite file")
        with self._db(readonly=True) as db:
            tables = {n for (n,) in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if not tables:
                return  # an empty SQLite file: adopted by the first put
            if "records" not in tables:
                raise ValueError(
                    f"store: {self.path} is a SQLite file but not a kpstudy campaign store "
                    f"(no records table; it has {', '.join(sorted(tables))})"
                )
            stored = None
            if "meta" in tables:
                row = db.execute("SELECT value FROM meta WHERE key = 'provenance'").fetchone()
                stored = None if row is None else json.loads(row[0])
            count = db.execute("SELECT COUNT(*) FROM records").fetchone()[0]
        if self.provenance is None:
            return
        if stored is None and count:
            raise ValueError(
                f"store: {self.path} holds {count} records of unknown provenance (written "
                "before stores recorded their checkpoint, data, settings and code); "
                "use another store"
            )
        if stored is not None and stored != _jsonable(self.provenance):
            raise ValueError(
                f"store: {self.path} was made by another campaign "
                f"({_differences(stored, _jsonable(self.provenance))}); use another store, "
                "or the checkpoint, data, settings and code that made this one"
            )

    def keys(self, *, errors: bool = True) -> set[str]:
        """The stored instances' keys (``errors=False``: leaving out ``'error'`` records)."""
        if not self.path.exists():
            return set()
        with self._db(readonly=True) as db:
            tables = {n for (n,) in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if "records" not in tables:
                return set()
            rows = db.execute("SELECT key, record FROM records").fetchall()
        return {k for k, r in rows if errors or json.loads(r).get("status") != "error"}

    def put(self, instance: Instance, record: dict) -> None:
        """Store ``record`` for ``instance`` (replacing an older one) in one transaction,
        creating the store with this provenance when it has none."""
        if self.provenance is None:
            raise ValueError("store: opened without a provenance, the store is read-only")
        mine = json.dumps(_jsonable(self.provenance), sort_keys=True)
        if not self.path.exists():
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ValueError(f"store: cannot create {self.path} ({exc})") from exc
        with self._db() as db:  # one transaction: provenance, then the record
            db.execute("CREATE TABLE IF NOT EXISTS records (key TEXT PRIMARY KEY, record TEXT)")
            db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT)")
            db.execute("INSERT OR IGNORE INTO meta VALUES ('provenance', ?)", (mine,))
            (stored,) = db.execute("SELECT value FROM meta WHERE key = 'provenance'").fetchone()
            if json.loads(stored) != json.loads(mine):  # another campaign got there first
                raise ValueError(
                    f"store: {self.path} was made by another campaign "
                    f"({_differences(json.loads(stored), json.loads(mine))}); use another store"
                )
            db.execute(
                "INSERT OR REPLACE INTO records VALUES (?, ?)",
                (instance.key, json.dumps(record)),
            )

    def frame(self, instances: Iterable[Instance] | None = None) -> pd.DataFrame:
        """One row per record: the instance's fields, then the record's (of ``instances``
        only, in their order, when given)."""
        stored = {}
        if self.path.exists():
            with self._db(readonly=True) as db:
                tables = {
                    n for (n,) in db.execute("SELECT name FROM sqlite_master WHERE type='table'")
                }
                if "records" in tables:
                    stored = dict(db.execute("SELECT key, record FROM records"))
        keys = list(stored) if instances is None else [i.key for i in instances if i.key in stored]
        rows = [{**json.loads(k), **json.loads(stored[k])} for k in keys]
        return pd.DataFrame(rows)


def provenance(settings: Settings) -> dict:
    """What makes a campaign's records: ``checkpoint`` (SHA-256 of its bytes), ``dataset``
    (SHA-256 of ``annotations.json`` and the perturbation sets' ``meta.json``),
    ``settings`` (the :class:`Settings` fields but the two paths) and ``code``
    (:func:`kpstudy.io.source_fingerprint`). Moving the files keeps it; retraining,
    regenerating, other settings or changed code do not."""
    _check_settings(settings)
    data = Path(settings.data_dir)
    dataset = hashlib.sha256()
    for path in [data / "annotations.json", *sorted(data.glob("perturbations/*/meta.json"))]:
        dataset.update(path.relative_to(data).as_posix().encode())
        dataset.update(path.read_bytes())
    rest = {k: v for k, v in asdict(settings).items() if k not in ("checkpoint", "data_dir")}
    for name in ("timeout", "pose_bound_timeout"):  # 60 and 60.0 are one setting
        rest[name] = None if rest[name] is None else float(rest[name])
    return {
        "checkpoint": hashlib.sha256(Path(settings.checkpoint).read_bytes()).hexdigest(),
        "dataset": dataset.hexdigest(),
        "settings": rest,
        "code": source_fingerprint(),
    }


def store_path(folder, name: str, settings: Settings) -> Path:
    """``folder/<name>-<fingerprint>.sqlite``, the fingerprint (12 hex digits) hashing the
    campaign's :func:`provenance`: records of a retrained model, of other settings or of
    changed code never mix with these."""
    text = json.dumps(_jsonable(provenance(settings)), sort_keys=True)
    return Path(folder) / f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:12]}.sqlite"


def _jsonable(value):
    """``value`` as it reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(value, sort_keys=True))


def _differences(stored: dict, mine: dict) -> str:
    """What differs between two provenances, in words (one line), such as ``its
    checkpoint, timeout 60.0 (here 999.0) differ``."""
    out = [name for name in ("checkpoint", "dataset", "code") if stored.get(name) != mine.get(name)]
    old, new = stored.get("settings") or {}, mine.get("settings") or {}
    out += [
        f"{k} {old.get(k)!r} (here {new.get(k)!r})"
        for k in sorted(set(old) | set(new))
        if old.get(k) != new.get(k)
    ]
    out = out or ["provenance"]
    return f"its {', '.join(out)} {'differs' if len(out) == 1 else 'differ'}"


def run_campaign(
    instances: list[Instance],
    store,
    settings: Settings,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
    on_record: Callable[[Instance, dict], None] | None = None,
    retry_errors: bool = False,
) -> pd.DataFrame:
    """Certify every instance the store lacks; return the records of ``instances``.

    Parameters
    ----------
    instances : list of Instance
    store : ResultStore or path
        Opened with this campaign's :func:`provenance`: a store made by another, or one that
        a running campaign holds, is refused (``ValueError`` naming ``store``) before any
        work; a new one is created with the first record.
    settings : Settings
        Its checkpoint, dataset and the instances' perturbation sets are loaded once
        before the store is opened; one that cannot be read is refused (``ValueError``
        naming ``checkpoint`` or ``data_dir`` and the file).
    workers : int
        Local worker processes (1: this process), each with ``cpu_count // workers`` torch
        threads. Ignored with ``scheduler``. A worker (or Dask task) takes one hull's
        instances at a time, so each hull's region search is made once. Workers exit
        when this process dies; SIGTERM (with no handler of the caller's) stops them and
        exits with status 143.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:port``): the instances run there. An
        address that does not answer is refused (``ValueError`` naming ``scheduler``).
    progress : bool
        A progress bar with the time left.
    on_record : callable, optional
        Called with each new record after it is stored.
    retry_errors : bool
        Also rerun the instances stored with status ``'error'``.

    Returns
    -------
    DataFrame
        One row per stored instance of ``instances``: its fields and its record. An
        instance that raised has ``status='error'``, ``error`` (the exception's type and
        message) and ``total_time`` (s) only.
    """
    campaign = _Campaign.open(instances, store, settings, retry_errors)
    try:
        _execute(
            [campaign], workers=workers, scheduler=scheduler, progress=progress, on_record=on_record
        )
    finally:
        campaign.close()
    return campaign.store.frame(instances)


@dataclass
class _Campaign:
    """One campaign's store, settings, the instances it still lacks and the lock it holds
    on the store (:meth:`close` lets it go)."""

    store: ResultStore
    settings: Settings
    missing: list[Instance]
    lock: _StoreLock | None = None

    @classmethod
    def open(cls, instances, store, settings: Settings, retry_errors: bool = False) -> _Campaign:
        """Check the settings and the inputs (:func:`_check_inputs`), open the store with
        their provenance and lock it: a store made by another campaign, or held by a running
        one, is refused here, before any work."""
        _check_settings(settings)
        instances = list(dict.fromkeys(instances))
        _check_inputs(settings, instances)
        path = store.path if isinstance(store, ResultStore) else store
        store = ResultStore(path, provenance(settings))
        lock = _StoreLock(store.path) if instances else None
        try:
            done = store.keys(errors=not retry_errors)
        except BaseException:
            if lock is not None:
                lock.release()
            raise
        return cls(store, settings, [i for i in instances if i.key not in done], lock)

    def close(self) -> None:
        """Let the store's lock go (nothing when it has none)."""
        if self.lock is not None:
            self.lock.release()
            self.lock = None


class _StoreLock:
    """The exclusive lock of a running campaign on its store: ``fcntl.flock`` on the file
    ``<store>.lock`` beside it, taken without waiting; a store that another campaign holds
    is refused (``ValueError`` naming ``store`` and the holder's pid, host and start).

    Why a lock and not claims of instances with leases in the store: the operating system
    drops a flock when its process dies, however it dies (SIGKILL, a crash, a lost
    machine's NFS lease), so there is no lease to renew, no clock to trust and no dead
    holder to detect; a second campaign has nothing to add that ``workers`` or a Dask
    ``scheduler`` would not, so refusing it loses nothing. The file holds the holder's
    pid, host and start time (for the refusal's message only) and is removed when the
    campaign ends, with the folders made for it if the store was not written (refused
    arguments leave nothing behind); one that a killed campaign left behind is taken
    over. On a file system without flock (some network mounts) or a system without
    ``fcntl`` the store is not locked.
    """

    def __init__(self, store: Path) -> None:
        self.store = Path(store)
        self.path = self.store.with_name(self.store.name + ".lock")
        self.fd = None
        try:
            import fcntl
        except ImportError:  # no flock here: campaigns on one store are not kept apart
            return
        self.made = [p for p in self.path.parents if not p.exists()]  # deepest first
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"store: cannot create {self.path.parent} ({exc})") from exc
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise ValueError(f"store: cannot lock {store} ({self.path}: {exc})") from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._holder(fd)
                os.close(fd)
                raise ValueError(
                    f"store: {store} is in use by a running campaign{holder}; wait for it "
                    "to end, or use another store"
                ) from None
            except OSError:  # no flock on this file system
                os.close(fd)
                return
            try:  # the holder before may have removed the file as it ended: lock the new one
                current = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                current = False
            if current:
                break
            os.close(fd)
        self.fd = fd
        since = time.strftime("%Y-%m-%d %H:%M:%S")
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "since": since}
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(holder).encode())

    @staticmethod
    def _holder(fd: int) -> str:
        """`` (pid …, host …, since …)`` from a held lock file, or nothing."""
        try:
            holder = json.loads(os.pread(fd, 4096, 0))
            return f" (pid {holder['pid']} on {holder['host']} since {holder['since']})"
        except (OSError, ValueError, KeyError, TypeError):
            return ""

    def release(self) -> None:
        """Remove the lock file, then let the lock go (in this order, so that a campaign
        that opened the old file retries on a new one)."""
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(self.fd)
        self.fd = None
        if not self.store.exists():
            for folder in self.made:  # empty unless another campaign wrote there meanwhile
                with contextlib.suppress(OSError):
                    folder.rmdir()


def _execute(
    campaigns: list[_Campaign],
    *,
    workers: int,
    scheduler: str | None,
    progress: bool,
    on_record: Callable[[Instance, dict], None] | None = None,
) -> None:
    """Run the missing hulls of every campaign in one pool (or this process, or Dask),
    storing each record in its campaign's store as it arrives. Hulls with the longest
    pose-bound time cap go first, so that the pool's last tasks are short ones."""
    _checks.integer(workers, "workers", minimum=1)
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
        raise ValueError(f"scheduler: expected a Dask scheduler address, got {scheduler!r}")
    tasks = [(c, group) for c in campaigns for group in _by_hull(c.missing)]
    tasks.sort(key=lambda task: -(task[0].settings.pose_bound_timeout or 0.0))
    if scheduler is not None or workers > 1:  # what _check_inputs loaded is not used here
        _context.cache_clear()
    client = _client(scheduler) if scheduler is not None and tasks else None
    bar = tqdm(
        total=sum(len(g) for _, g in tasks), desc="instances", unit="inst", disable=not progress
    )

    def finish(task, records):
        campaign, group = task
        for instance, record in zip(group, records):
            campaign.store.put(instance, record)
            bar.update()
            if on_record is not None:
                on_record(instance, record)

    try:
        if not tasks:
            pass
        elif client is not None:
            from distributed import as_completed as dask_completed

            with client:
                futures = {
                    client.submit(_attempt_hull, g, c.settings, pure=False): (c, g)
                    for c, g in tasks
                }
                for future in dask_completed(futures):
                    finish(futures[future], future.result())
        elif workers == 1:
            for task in tasks:
                finish(task, _attempt_hull(task[1], task[0].settings))
        else:
            threads = max(1, (os.cpu_count() or 1) // int(workers))
            with _sigterm_exits():
                pool = ProcessPoolExecutor(
                    int(workers),
                    mp_context=get_context("spawn"),
                    initializer=_init,
                    initargs=(threads, os.getpid()),
                )
                try:
                    futures = {pool.submit(_attempt_hull, g, c.settings): (c, g) for c, g in tasks}
                    for future in as_completed(futures):
                        finish(futures[future], future.result())
                    pool.shutdown()
                except BaseException:  # Ctrl-C, SIGTERM, a failed store: no worker outlives it
                    _stop(pool)
                    raise
    finally:
        bar.close()


def _client(scheduler: str):
    """A Dask client of ``scheduler``; ``ValueError`` naming ``scheduler`` when nothing
    answers there (a TCP address is tried first, for a quick refusal)."""
    import socket
    from urllib.parse import urlsplit

    address = scheduler if "://" in scheduler else f"tcp://{scheduler}"
    parts = urlsplit(address)
    if parts.scheme in ("tcp", "tls"):
        try:
            host, port = parts.hostname, parts.port
        except ValueError:
            host = port = None
        if not host or port is None:
            raise ValueError(
                f"scheduler: expected an address such as tcp://host:8786, got {scheduler!r}"
            )
        try:
            socket.create_connection((host, port), timeout=10).close()
        except OSError as exc:
            raise ValueError(
                f"scheduler: no Dask scheduler answers at {scheduler} ({exc.strerror or exc})"
            ) from exc
    from distributed import Client

    try:
        return Client(scheduler, timeout=20)
    except (OSError, TimeoutError, ValueError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"scheduler: cannot connect to {scheduler} ({message})") from exc


@contextlib.contextmanager
def _sigterm_exits():
    """SIGTERM raises ``SystemExit(143)`` in the block (main thread, default handler only),
    so that the pool's cleanup stops the workers."""
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return

    def exit_(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, exit_)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now: cancel what waits, kill the workers (also those mid-instance)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        with contextlib.suppress(Exception):
            process.kill()
    for process in processes:
        with contextlib.suppress(Exception):
            process.join(5)
    pool.shutdown(wait=False, cancel_futures=True)


def run_study(
    checkpoints: dict[str, str],
    data_dir,
    kinds: Iterable[str],
    folder,
    *,
    grid_options: dict,
    tolerance_units: Iterable[str] = ("heatmap",),
    pose_bound: dict[str, dict] | None = None,
    allocation: dict[str, dict] | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    **settings,
) -> pd.DataFrame:
    """Every campaign of one study table: each model × tolerance reading × kind, one
    resumable store each (:func:`store_path` under ``folder``). Their hulls share one
    pool of ``workers`` (started once; a worker keeps the models and allocations it has
    loaded), the hulls with the longest pose-bound time cap first.

    Parameters
    ----------
    checkpoints : dict
        ``{model name: checkpoint path}``.
    data_dir : path
    kinds : iterable of str
        Perturbation kinds (:func:`grid`).
    folder : path
        Where the stores go.
    grid_options : dict
        :func:`grid`'s keywords (``alphas``, ``kappas``, ``seeds``, ``ms``, …).
    tolerance_units : iterable of str
        The readings (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`) the allocation method
        runs under. The pose-bound method has no tolerances: it runs with the first only.
    pose_bound : dict, optional
        ``{model name: Settings fields of the pose-bound method}``; a model left out
        skips it.
    allocation : dict, optional
        ``{model name: {'method', 'nodes', 'timeout'}}``: the allocation method's bounds
        and budget for that model in place of ``settings``' (e.g. forward bounds where
        the zonotope cannot decide within any affordable budget); a model left out, or a
        field left out, keeps ``settings``'.
    workers, scheduler, progress :
        :func:`run_campaign`'s.
    **settings :
        The other :class:`Settings` fields (``timeout``, ``nodes``, …).

    Returns
    -------
    DataFrame
        The records of every campaign with ``model`` and ``tolerance_units`` columns.
    """
    readings = list(tolerance_units)
    if not readings:
        raise ValueError("tolerance_units: expected one or more readings, got none")
    allocation = allocation or {}
    for model, chosen in allocation.items():
        if (
            model not in checkpoints
            or not isinstance(chosen, dict)
            or not set(chosen) <= set(ALLOCATION_SETTINGS)
        ):
            raise ValueError(
                f"allocation: expected {{model of checkpoints: {{{', '.join(ALLOCATION_SETTINGS)}"
                f"}}}}, got {model!r}: {chosen!r}"
            )
    campaigns, labels = [], []
    try:
        for model, checkpoint in checkpoints.items():
            for units in readings:
                extra = (pose_bound or {}).get(model, {}) if units == readings[0] else {}
                chosen = {**settings, **allocation.get(model, {}), **extra}
                config = Settings(str(checkpoint), str(data_dir), tolerance_units=units, **chosen)
                for kind in kinds:
                    instances = grid(data_dir, kind, **grid_options)
                    store = store_path(folder, kind, config)
                    campaigns.append((_Campaign.open(instances, store, config), instances))
                    labels.append(dict(model=model, tolerance_units=units))
        _execute([c for c, _ in campaigns], workers=workers, scheduler=scheduler, progress=progress)
    finally:
        for c, _ in campaigns:
            c.close()
    frames = [c.store.frame(i).assign(**label) for (c, i), label in zip(campaigns, labels)]
    return pd.concat(frames, ignore_index=True)


def _attempt_hull(instances: list[Instance], settings: Settings) -> list[dict]:
    """:func:`run_hull`, an exception turned into an ``'error'`` record for each of the
    hull's instances (the campaign goes on)."""
    start = time.perf_counter()
    try:
        return run_hull(instances, settings)
    except Exception as exc:  # noqa: BLE001 - any failure of one hull is its result
        error = {
            "status": "error",
            "error": f"{type(exc).__name__}: {exc}",
            "total_time": time.perf_counter() - start,
        }
        return [dict(error) for _ in instances]


def _by_hull(instances: list[Instance]) -> list[list[Instance]]:
    """``instances`` grouped by hull (kind, seed image, m, overlap class, level), in the
    order of each hull's first instance."""
    groups: dict[tuple, list[Instance]] = {}
    for i in instances:
        groups.setdefault((i.kind, i.image_id, i.m, i.overlapping, i.level), []).append(i)
    return list(groups.values())


def instance_vertices(instance: Instance, data_dir, hull_seed: int = 0):
    """The hull's vertices ``(n+1, H, W, 3)`` of ``instance`` (the seed image first), as
    :func:`data_gen.perturb.hull_vertices` draws them from ``data_dir``."""
    from data_gen.perturb import hull_vertices

    return hull_vertices(
        data_dir,
        instance.image_id,
        instance.kind,
        instance.m,
        instance.overlapping,
        hull_seed,
        level=instance.level,
    )


def run_hull(instances: list[Instance], settings: Settings) -> list[dict]:
    """Certify the instances of one hull (one group of :func:`_by_hull`: its α, κ cells)
    in this process, one record each: what depends on the hull alone, such as the
    pose-bound method's region search, is made once (:func:`kpstudy.certify.hull.certify_cells`)."""
    from data_gen.perturb import load_perturbations
    from kpstudy.certify.hull import certify_cells

    first = instances[0]
    if len(_by_hull(instances)) != 1:
        raise ValueError(f"instances: expected the instances of one hull, got {instances!r}")
    backbone, seed_of = _context(settings.checkpoint, settings.data_dir)
    vertices = instance_vertices(first, settings.data_dir, settings.hull_seed)
    cells = [(i.alpha, i.kappa) for i in instances]
    seed = seed_of(first.image_id)
    records = certify_cells(backbone, vertices, seed, cells, **settings.certify_options())
    clipped = 0.0
    if first.kind in GLOBAL_KINDS:
        rows = load_perturbations(settings.data_dir, first.kind)["images"]
        clipped = sum(
            r["clipped_fraction"]
            for r in rows
            if r["image_id"] == first.image_id and np.isclose(r["level"], first.level)
        )
    peak = peak_memory_mib()
    for record in records:
        record["clipped_fraction"] = float(clipped)
        record["peak_memory_mib"] = peak
    return records


def peak_memory_mib() -> float:
    """This process's largest resident set so far, MiB (``getrusage``'s ``ru_maxrss``,
    KiB on Linux): in a campaign worker, what the hulls it has run needed at most."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@functools.lru_cache(maxsize=2)
def _context(checkpoint: str, data_dir: str):
    """The backbone and a seed-image lookup over the test split, loaded once per process."""
    from kpstudy.certify.allocation_method import SeedImage
    from kpstudy.models.data import load_keypoint_set
    from kpstudy.models.training import load_checkpoint

    backbone, _ = load_checkpoint(checkpoint)
    test = load_keypoint_set(data_dir, "test", backbone.input_size)
    index = {int(image_id): i for i, image_id in enumerate(test.image_ids)}

    def seed_of(image_id: int) -> SeedImage:
        return SeedImage.from_keypoint_set(test, index[image_id])

    seed_of.image_ids = frozenset(index)
    return backbone, seed_of


def _init(threads: int, parent: int) -> None:
    """A pool worker's start: die with ``parent`` (the campaign's pid), set torch threads."""
    _die_with(parent)
    import torch

    torch.set_num_threads(threads)


def _die_with(parent: int, poll: float = 0.5) -> None:
    """Exit this process when ``parent`` dies: ``PR_SET_PDEATHSIG`` on Linux, and a daemon
    thread that checks the parent pid every ``poll`` seconds (other systems, and the
    parent that died before the signal was armed)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1: PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)

    def watch():
        while os.getppid() == parent:
            time.sleep(poll)
        os._exit(1)

    threading.Thread(target=watch, name="kpstudy-parent-watch", daemon=True).start()


def _check_settings(settings: Settings) -> None:
    if not isinstance(settings, Settings):
        raise ValueError(f"settings: expected a Settings, got {type(settings).__name__}")
    if not Path(settings.checkpoint).is_file():
        raise FileNotFoundError(f"checkpoint: no file at {settings.checkpoint}")
    if not Path(settings.data_dir, "annotations.json").is_file():
        raise FileNotFoundError(f"data_dir: no data_gen dataset at {settings.data_dir}")
    settings.allocation_options()
    _checks.integer(settings.check_samples, "check_samples", minimum=0)
    _checks.integer(settings.hull_seed, "hull_seed", minimum=0)
    settings.pose_bound_options()
    from kpstudy.pose.allocation import allocation_scale

    allocation_scale(settings.tolerance_units, None)  # checks the name


def _check_inputs(settings: Settings, instances: list[Instance]) -> None:
    """Load and check, once, what every instance reads: the checkpoint and the dataset's
    test split, annotations and images (:func:`_context`, which this process then reuses
    when it runs the instances itself), and the perturbation set of each kind among
    ``instances`` (its ``meta.json``, and the files of their seed images). One that cannot
    be read raises a one-line ``ValueError`` naming ``checkpoint`` or ``data_dir`` (or
    ``kind``, for a set's ``meta.json``) and the file."""
    from data_gen.perturb import load_perturbations

    data = settings.data_dir
    try:
        _, seed_of = _context(settings.checkpoint, data)
    except ValueError as exc:  # load_checkpoint and load_keypoint_set name what they read
        raise ValueError(_one_line(exc)) from exc
    except Exception as exc:  # noqa: BLE001 - an image that cannot be read, …
        raise ValueError(
            f"data_dir: cannot read the test split of {data} ({_one_line(exc)})"
        ) from exc
    for kind in dict.fromkeys(i.kind for i in instances):
        ids = {i.image_id for i in instances if i.kind == kind}
        folder = Path(data, "perturbations", kind)
        try:
            rows = [r for r in load_perturbations(data, kind)["images"] if r["image_id"] in ids]
            files = [folder / r[name] for r in rows for name in ("file", "seed_file") if name in r]
        except (KeyError, TypeError) as exc:
            raise ValueError(
                f"data_dir: {folder / 'meta.json'} is not a data_gen perturbation set "
                f"({type(exc).__name__}: {exc})"
            ) from exc
        except ValueError as exc:
            raise ValueError(_one_line(exc)) from exc
        for path in files:
            if not path.is_file() or not path.stat().st_size:
                raise ValueError(
                    f"data_dir: {path} of the {kind} perturbation set is missing or empty; "
                    "make the set again (python -m data_gen perturb)"
                )
        strangers = sorted(ids - seed_of.image_ids)
        if strangers:
            raise ValueError(
                f"data_dir: the {kind} set's seed images {strangers} are not test images of "
                f"{data} (a perturbation set of another dataset?)"
            )


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(line.strip() for line in str(exc).splitlines()) or type(exc).__name__


def _positive_list(values, name: str) -> list[float]:
    out = [float(v) for v in values]
    if not out or any(not v > 0 for v in out):
        raise ValueError(f"{name}: expected one or more values > 0, got {out}")
    return out
