"""The verification tables of paper §8.4 from campaign records, the paper's numbers beside ours.

A campaign record (:func:`kpstudy.study.campaign.run_campaign`) is one instance: its grid
fields (``kind``, ``m``, ``overlapping``, ``level``, ``alpha``, ``kappa``) and the
certificate's (``status``, ``time``, ``seed_inside``, …). Each table groups records by
its axes and reports, per cell:

* ``instances``, ``seeds_inside`` (seeds whose target-model pose error lies in Ξ) and
  the counts of ``holds`` / ``violated`` / ``unknown`` / ``not_certifiable`` (the pixel
  grid alone exceeds the tolerance: the nearest heatmap pixels of the exact keypoints
  already move the pose out of ε / κ, so no cell certifies the instance at this heatmap
  resolution) and ``violated_at_seed`` (the counterexample is the seed image itself,
  λ = 0);
* ``errors``: instances that could not be certified (status ``error``, e.g. a seed with
  a keypoint outside the heatmap). They count in ``instances`` only: holds + violated +
  unknown + not_certifiable + errors = instances, and every other column is over the
  other instances;
* ``verified_rate`` = holds among the seeds inside Ξ ÷ seeds inside Ξ (paper §8.4; NaN
  when no seed is inside; a ``not_certifiable`` seed inside Ξ stays in the denominator),
  ``verified_rate_lo`` – ``verified_rate_hi``: its 95 % Wilson interval
  (:func:`kpstudy.study.trends.rate_interval`); ``decided``: the fraction of instances that
  are ``holds`` or ``violated``; ``capped`` (records that store ``stopped``): instances
  whose search the time cap ended (their verdict depends on the machine; node budgets
  decide the others);
* ``dv_mean``, ``dv_zero``: mean allocated tolerance (heatmap px: integers, or the cells'
  float half-widths) and the fraction of coordinates allocated 0 (one-pixel cells), over
  the instances that have cells (not ``not_certifiable``);
* ``time_mean`` ± ``time_std`` (over the population, ``ddof = 0``), ``time_median`` and
  the quartiles ``time_q1`` – ``time_q3``: verification seconds over all instances of the
  cell (the paper's standard deviations exceed its means: the median says more);
  ``time_holds_mean``, ``time_violated_mean`` and ``time_unknown_mean``: over its
  proofs (``holds``), its refutations (``violated``) and its undecided instances
  (``unknown``, a budget spent) only (NaN without any), so that proofs compare with
  proofs;
* ``paper_rate`` with ``paper_rate_lo`` – ``paper_rate_hi`` (the 95 % interval its 200
  seeds imply, :func:`kpstudy.study.trends.paper_interval`), ``paper_time_mean``,
  ``paper_time_std`` (ModelVerification.jl on an RTX A4000; NaN where the paper has no
  cell);
* with the pose-bound method's records (``pb_*``, :mod:`kpstudy.certify.pose_bound_method`):
  ``pb_holds``, ``pb_violated``, ``pb_unknown``, ``pb_decided``, ``pb_capped`` (as ``capped``,
  from ``pb_stopped``), ``pb_seeds_inside`` (seeds whose *argmax* → PnP pose lies in Ξ,
  ``pb_seed_inside``: the pipeline this method certifies; the target model's ``seed_inside``
  for records from before it was stored), ``pb_verified_rate`` (holds among those ÷ those)
  with ``pb_verified_rate_lo`` – ``pb_verified_rate_hi``, ``pb_time_mean`` ±
  ``pb_time_std``, ``pb_time_median``, ``pb_time_q1`` – ``pb_time_q3`` (and
  ``pb_time_holds_mean``, ``pb_time_violated_mean``, ``pb_time_unknown_mean`` as above);
  ``pb_by_witness``, ``pb_by_enumeration``,
  ``pb_by_linearised``: the instances each rule decided (``pb_rule``; records from before it
  was stored were decided by ``'witness'`` when ``violated`` and by ``'linearised'``
  otherwise, and are counted so), with ``pb_enumeration_holds`` the ``holds`` among those by
  enumeration (exact for the argmax → PnP pipeline); ``pb_nonlinear_outside`` (``holds``
  whose PnP re-solved at region corners leaves Ξ: the linearised bound's error, which the
  allocation method shares; never a ``holds`` by enumeration) and ``pb_only`` /
  ``allocation_only``: seeds inside Ξ that one method verifies and the other does not.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd

from kpstudy.pose.geometry import POSE_AXES, tolerance
from kpstudy.study.trends import paper_interval, rate_interval

__all__ = [
    "NODE_MARKS",
    "PAPER_T_GLOBAL",
    "PAPER_T_LOCAL",
    "PAPER_T_PROB",
    "PAPER_T_RESNET",
    "decided_by_nodes",
    "instance_label",
    "plot_pose_bounds",
    "pose_bound_ratios",
    "reading_comparison",
    "summarise",
    "t_global",
    "t_local",
    "t_prob",
    "t_resnet",
]

#: Paper Tables 3–4: (m, overlapping, κ, α) → (time mean s, time std s, verified rate).
PAPER_T_LOCAL = {
    (2, False, 1.0, 1.0): (38.3, 56.7, 0.550),
    (2, False, 1.0, 1.5): (11.9, 11.1, 0.885),
    (2, False, 1.5, 1.0): (81.5, 79.7, 0.169),
    (2, False, 1.5, 1.5): (47.1, 69.0, 0.556),
    (2, True, 1.0, 1.0): (82.1, 128.3, 0.422),
    (2, True, 1.0, 1.5): (31.1, 29.4, 0.741),
    (2, True, 1.5, 1.0): (133.1, 127.3, 0.131),
    (2, True, 1.5, 1.5): (72.4, 79.6, 0.448),
    (3, False, 1.0, 1.0): (63.3, 89.2, 0.558),
    (3, False, 1.0, 1.5): (16.9, 12.3, 0.885),
    (3, False, 1.5, 1.0): (104.9, 188.3, 0.166),
    (3, False, 1.5, 1.5): (60.7, 74.0, 0.553),
    (3, True, 1.0, 1.0): (87.9, 87.4, 0.367),
    (3, True, 1.0, 1.5): (47.7, 44.7, 0.651),
    (3, True, 1.5, 1.0): (154.8, 127.4, 0.126),
    (3, True, 1.5, 1.5): (98.3, 96.2, 0.389),
    (4, False, 1.0, 1.0): (73.1, 103.8, 0.553),
    (4, False, 1.0, 1.5): (23.2, 16.5, 0.855),
    (4, False, 1.5, 1.0): (127.7, 105.4, 0.167),
    (4, False, 1.5, 1.5): (79.1, 101.0, 0.531),
    (4, True, 1.0, 1.0): (109.2, 101.8, 0.280),
    (4, True, 1.0, 1.5): (60.4, 36.7, 0.504),
    (4, True, 1.5, 1.0): (184.3, 132.5, 0.106),
    (4, True, 1.5, 1.5): (110.1, 87.7, 0.294),
}

#: Paper Tables 5–6: (kind, level, κ, α) → (time mean s, time std s, verified rate).
PAPER_T_GLOBAL = {
    ("contrast", 5e-4, 1.0, 1.0): (79.7, 105.5, 0.570),
    ("contrast", 5e-4, 1.0, 1.5): (15.4, 4.9, 0.915),
    ("contrast", 5e-4, 1.5, 1.0): (133.9, 95.5, 0.173),
    ("contrast", 5e-4, 1.5, 1.5): (83.2, 105.0, 0.571),
    ("contrast", 5e-3, 1.0, 1.0): (88.6, 112.3, 0.565),
    ("contrast", 5e-3, 1.0, 1.5): (19.6, 5.7, 0.905),
    ("contrast", 5e-3, 1.5, 1.0): (159.0, 111.1, 0.168),
    ("contrast", 5e-3, 1.5, 1.5): (92.0, 108.1, 0.567),
    ("contrast", 1e-2, 1.0, 1.0): (176.3, 232.9, 0.560),
    ("contrast", 1e-2, 1.0, 1.5): (48.7, 17.7, 0.874),
    ("contrast", 1e-2, 1.5, 1.0): (304.1, 243.6, 0.173),
    ("contrast", 1e-2, 1.5, 1.5): (200.0, 249.4, 0.568),
    ("brightness", 1.0, 1.0, 1.0): (135.0, 171.5, 0.570),
    ("brightness", 1.0, 1.0, 1.5): (32.7, 12.4, 0.915),
    ("brightness", 1.0, 1.5, 1.0): (236.4, 164.0, 0.150),
    ("brightness", 1.0, 1.5, 1.5): (144.7, 164.5, 0.577),
    ("brightness", 2.0, 1.0, 1.0): (223.4, 301.9, 0.560),
    ("brightness", 2.0, 1.0, 1.5): (64.6, 22.5, 0.885),
    ("brightness", 2.0, 1.5, 1.0): (373.5, 309.2, 0.148),
    ("brightness", 2.0, 1.5, 1.5): (225.1, 266.0, 0.576),
}

#: Paper §8.4, ResNet-18 block occlusions at κ = 1, α = 1.5: overlapping → (mean, std, rate).
PAPER_T_RESNET = {False: (314.4, 227.0, 0.935), True: (1571.7, 1213.5, 0.940)}

#: Paper Table 2 (soundness, completeness) by (κ, α); "<6.67e-9" is entered as 0.
PAPER_T_PROB = {
    (1.0, 0.5): (1.0, 1.93e-6),
    (1.0, 1.0): (0.998978, 3.07e-5),
    (1.0, 1.5): (0.996596, 4.85e-5),
    (1.0, 2.0): (0.988339, 6.20e-5),
    (1.5, 0.5): (1.0, 0.0),
    (1.5, 1.0): (0.999993, 1.00e-6),
    (1.5, 1.5): (0.999887, 2.00e-6),
    (1.5, 2.0): (0.999890, 3.67e-6),
    (2.0, 0.5): (1.0, 0.0),
    (2.0, 1.0): (1.0, 0.0),
    (2.0, 1.5): (1.0, 3.33e-7),
    (2.0, 2.0): (0.999999, 6.67e-7),
}

_STATUSES = ("holds", "violated", "unknown", "not_certifiable")
_PB_RULES = ("witness", "enumeration", "linearised")  # kpstudy.certify.pose_bound_method's pb_rule


def summarise(records: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Per cell of ``by``: counts, verified rate and time (module docstring)."""
    need = {*by, "status"}
    if "status" in records and (records["status"] != "error").any():
        need |= {"time", "seed_inside"}
    missing = sorted(need - set(records.columns))
    if missing:
        raise ValueError(f"records: expected campaign records with columns {missing}")
    records = records.assign(
        **{c: np.nan for c in ("time", "seed_inside") if c not in records}
    )  # only error records: no certificate columns
    rows = []
    for key, everything in records.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        failed = everything["status"] == "error"
        cell = everything[~failed]
        inside = cell["seed_inside"].astype(bool)
        holds = cell["status"] == "holds"
        row = dict(zip(by, key))
        row["instances"] = len(everything)
        row["seeds_inside"] = int(inside.sum())
        row.update({s: int((cell["status"] == s).sum()) for s in _STATUSES})
        row["errors"] = int(failed.sum())
        row["violated_at_seed"] = int(
            sum(
                status == "violated" and isinstance(lam, (list, str)) and max(_list(lam)) <= 1e-9
                for status, lam in zip(
                    cell["status"], cell.get("counterexample", [None] * len(cell))
                )
            )
        )
        row["verified_rate"] = (
            float((holds & inside).sum() / inside.sum()) if inside.any() else np.nan
        )
        row["verified_rate_lo"], row["verified_rate_hi"] = rate_interval(
            int((holds & inside).sum()), int(inside.sum())
        )
        decided = cell["status"].isin(["holds", "violated"])
        row["decided"] = float(decided.mean()) if len(cell) else np.nan
        if "stopped" in cell:
            row["capped"] = int((cell["stopped"] == "time").sum())
        if "dv" in cell and len(cell):
            row["dv_mean"], row["dv_zero"] = _dv(cell)
        row.update(_times(cell["time"], "time"))
        row["time_holds_mean"] = _mean(cell["time"][holds])
        row["time_violated_mean"] = _mean(cell["time"][cell["status"] == "violated"])
        row["time_unknown_mean"] = _mean(cell["time"][cell["status"] == "unknown"])
        if "pb_status" in cell and cell["pb_status"].notna().any():
            pb = cell["pb_status"] == "holds"
            row["pb_holds"] = int(pb.sum())
            row["pb_violated"] = int((cell["pb_status"] == "violated").sum())
            row["pb_unknown"] = int((cell["pb_status"] == "unknown").sum())
            row["pb_decided"] = float(
                cell["pb_status"].isin(["holds", "violated"]).sum()
                / cell["pb_status"].notna().sum()
            )
            pb_inside = _pb_inside(cell, inside)
            row["pb_seeds_inside"] = int(pb_inside.sum())
            row["pb_verified_rate"] = (
                float((pb & pb_inside).sum() / pb_inside.sum()) if pb_inside.any() else np.nan
            )
            row["pb_verified_rate_lo"], row["pb_verified_rate_hi"] = rate_interval(
                int((pb & pb_inside).sum()), int(pb_inside.sum())
            )
            row.update(_times(cell["pb_time"], "pb_time"))
            row["pb_time_holds_mean"] = _mean(cell["pb_time"][pb])
            row["pb_time_violated_mean"] = _mean(cell["pb_time"][cell["pb_status"] == "violated"])
            row["pb_time_unknown_mean"] = _mean(cell["pb_time"][cell["pb_status"] == "unknown"])
            row["pb_capped"] = (
                int((cell["pb_stopped"] == "time").sum()) if "pb_stopped" in cell else np.nan
            )
            rules = _pb_rules(cell)
            row.update({f"pb_by_{r}": int((rules == r).sum()) for r in _PB_RULES})
            row["pb_enumeration_holds"] = int((pb & (rules == "enumeration")).sum())
            row["pb_nonlinear_outside"] = int(
                sum(
                    bool(ok) and np.any(np.asarray(_list(n)) > eps)
                    for ok, n, eps in zip(pb, cell["pb_nonlinear"], _eps(cell))
                )
            )
            row["pb_only"] = int((pb & ~holds & inside).sum())
            row["allocation_only"] = int((holds & ~pb & inside).sum())
        if "argmax_outside" in cell:
            row["argmax_outside"] = float(pd.to_numeric(cell["argmax_outside"][holds]).mean())
        rows.append(row)
    columns = [
        *by,
        "instances",
        "seeds_inside",
        *_STATUSES,
        "errors",
        "violated_at_seed",
        "verified_rate",
        "verified_rate_lo",
        "verified_rate_hi",
        "decided",
        "dv_mean",
        "dv_zero",
        *_TIME_COLUMNS,
        "time_holds_mean",
        "time_violated_mean",
        "time_unknown_mean",
    ]
    if "pb_status" in records:
        columns += [
            "pb_holds",
            "pb_violated",
            "pb_unknown",
            "pb_decided",
            "pb_capped",
            "pb_seeds_inside",
            "pb_verified_rate",
            "pb_verified_rate_lo",
            "pb_verified_rate_hi",
            *(f"pb_{c}" for c in _TIME_COLUMNS),
            "pb_time_holds_mean",
            "pb_time_violated_mean",
            "pb_time_unknown_mean",
            *(f"pb_by_{r}" for r in _PB_RULES),
            "pb_enumeration_holds",
            "pb_nonlinear_outside",
            "pb_only",
            "allocation_only",
        ]
    if "argmax_outside" in records:
        columns.append("argmax_outside")
    if "stopped" in records:
        columns.insert(columns.index("decided") + 1, "capped")
    return pd.DataFrame(rows, columns=columns)


#: Per cell, the seconds of all its instances: mean, standard deviation, median, quartiles.
_TIME_COLUMNS = ("time_mean", "time_std", "time_median", "time_q1", "time_q3")


def _times(values: pd.Series, prefix: str) -> dict[str, float]:
    """``{prefix}_mean``, ``_std`` (``ddof = 0``), ``_median``, ``_q1``, ``_q3`` of the
    seconds ``values`` (NaN entries left out; all NaN without any)."""
    values = pd.to_numeric(values, errors="coerce").dropna()
    if not len(values):
        return {f"{prefix}{c[4:]}": float("nan") for c in _TIME_COLUMNS}
    q1, median, q3 = np.quantile(values.to_numpy(np.float64), [0.25, 0.5, 0.75])
    numbers = (values.mean(), values.std(ddof=0), median, q1, q3)
    return {f"{prefix}{c[4:]}": float(v) for c, v in zip(_TIME_COLUMNS, numbers)}


def instance_label(row) -> str:
    """The words that name a campaign record or a verification table's cell: model,
    tolerance reading, kind, image id, α, κ, m, level, overlapping or not, each where
    ``row`` (a record or table row: a dict or Series, stored or read back from CSV) has
    it and it is not NaN.

    Examples
    --------
    >>> instance_label(dict(model="cnn", tolerance_units="heatmap", kind="objects",
    ...                     image_id=3, alpha=1.5, kappa=1.0, m=2, overlapping=False))
    'cnn heatmap objects image 3 α=1.5 κ=1 m=2 non-overlapping'
    >>> instance_label(dict(kind="contrast", level=5e-4, kappa=1.0, alpha=1.0, m=float("nan")))
    'contrast α=1 κ=1 level=0.0005'
    """
    words = [_word(row.get(c)) for c in ("model", "tolerance_units", "kind")]
    if _present(row.get("image_id")):
        words.append(f"image {_word(row['image_id'])}")
    for column, label in (("alpha", "α"), ("kappa", "κ"), ("m", "m"), ("level", "level")):
        if _present(row.get(column)):
            words.append(f"{label}={_word(row[column])}")
    if _present(row.get("overlapping")):
        overlapping = row["overlapping"]
        if isinstance(overlapping, str):  # CSV text of a column mixing bools and blanks
            overlapping = overlapping.strip().lower() in ("true", "1")
        words.append("overlapping" if overlapping else "non-overlapping")
    return " ".join(w for w in words if w)


def _present(value) -> bool:
    """Whether a record's field holds a value (not None, NaN or blank)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return False
    return not (isinstance(value, (float, np.floating)) and np.isnan(value))


def _word(value) -> str:
    """A field's value as a word: whole numbers as integers (``3``, ``1``), others by
    ``:g`` (``1.5``, ``0.0005``), ``''`` for an absent one."""
    if not _present(value):
        return ""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return str(int(value)) if float(value).is_integer() else f"{value:g}"
    return str(value)


def _dv(cell: pd.DataFrame) -> tuple[float, float]:
    """Mean allocated tolerance and the fraction of zero coordinates over the records
    of ``cell`` that have cells: ``dv`` a list (stored, or JSON text from a CSV) of ints
    or float half-widths; ``not_certifiable`` records and those without a ``dv`` are left
    out (NaN, NaN without any)."""
    parts = []
    for status, value in zip(cell["status"], cell["dv"]):
        value = _list(value)
        if status != "not_certifiable" and isinstance(value, (list, tuple, np.ndarray)):
            parts.append(np.ravel(np.asarray(value, dtype=np.float64)))
    dv = np.concatenate(parts) if parts else np.array([])
    dv = dv[np.isfinite(dv)]
    if not len(dv):
        return float("nan"), float("nan")
    return float(dv.mean()), float(np.mean(dv == 0))


def _mean(values: pd.Series) -> float:
    """The mean of ``values`` in seconds, NaN when there are none."""
    values = pd.to_numeric(values, errors="coerce").dropna()
    return float(values.mean()) if len(values) else float("nan")


def _pb_inside(cell: pd.DataFrame, inside: pd.Series) -> pd.Series:
    """Per record, whether the seed's argmax → PnP pose lies in Ξ (``pb_seed_inside``: the
    pipeline the pose-bound method certifies); records from before it was stored count
    the target model's ``seed_inside``."""
    if "pb_seed_inside" not in cell:
        return inside
    return cell["pb_seed_inside"].where(cell["pb_seed_inside"].notna(), inside).astype(bool)


def _list(value) -> list:
    """A list field of a record, as stored (a list) or read back from CSV (JSON text, or
    Python's text of a list: ``inf`` and ``nan`` included)."""
    if not isinstance(value, str):
        return value
    return json.loads(re.sub(r"\b(inf|nan)\b", lambda m: _JSON_FLOATS[m[1]], value))


_JSON_FLOATS = {"inf": "Infinity", "nan": "NaN"}


def _pb_rules(cell: pd.DataFrame) -> pd.Series:
    """The rule that decided each record's ``pb_status`` (:mod:`kpstudy.certify.pose_bound_method`):
    ``pb_rule`` where stored, else the only rules of the code before it (``'witness'``
    for ``violated``, ``'linearised'`` for ``holds`` / ``unknown``); None without a
    ``pb_status`` (e.g. an ``error`` record)."""
    old = {"violated": "witness", "holds": "linearised", "unknown": "linearised"}
    inferred = cell["pb_status"].map(old)
    if "pb_rule" not in cell:
        return inferred
    return cell["pb_rule"].where(cell["pb_rule"].isin(_PB_RULES), inferred)


def _eps(cell: pd.DataFrame) -> list[np.ndarray]:
    """Ξ's half-widths ``(6,)`` of each record, from its α."""
    return [tolerance(a) for a in cell["alpha"]]


def t_prob(table: pd.DataFrame) -> pd.DataFrame:
    """T-prob (paper Table 2): a :func:`kpstudy.pose.montecarlo.soundness_completeness_table`
    with the paper's soundness and completeness beside ours."""
    out = table.copy()
    paper = [PAPER_T_PROB.get((k, a), (np.nan, np.nan)) for k, a in zip(out.kappa, out.alpha)]
    out["paper_soundness"] = [p[0] for p in paper]
    out["paper_completeness"] = [p[1] for p in paper]
    return out


def _by_model(records: pd.DataFrame, by: list[str]) -> list[str]:
    """``by``, led by ``model`` and ``tolerance_units`` when the records have them."""
    return [*(c for c in ("model", "tolerance_units") if c in records), *by]


def _readings(records: pd.DataFrame) -> pd.DataFrame:
    """``records`` with ``tolerance_units`` filled in (``'heatmap'`` before the field)."""
    if "tolerance_units" not in records:
        return records
    return records.assign(tolerance_units=records["tolerance_units"].fillna("heatmap"))


def reading_comparison(table: pd.DataFrame, ours: str, paper: str, name: str) -> str | None:
    """One sentence: per tolerance reading of ``table``, the mean ``|ours − paper|`` over
    the cells where both exist, beside the paper's own spread over those cells (its
    standard deviation); which reading is nearer and by how much. None without two
    readings or any paper cell."""
    if "tolerance_units" not in table or table["tolerance_units"].nunique() < 2:
        return None
    gaps = {}
    for units, part in table.groupby("tolerance_units", sort=True):
        both = part[[ours, paper]].apply(pd.to_numeric, errors="coerce").dropna()
        if len(both):
            gaps[units] = (float((both[ours] - both[paper]).abs().mean()), len(both))
    if len(gaps) < 2:
        return None
    cells = table[paper].apply(pd.to_numeric, errors="coerce").dropna()
    spread = float(cells.std(ddof=0)) if len(cells) else float("nan")
    (near, (g_near, n)), (far, (g_far, _)) = sorted(gaps.items(), key=lambda kv: kv[1][0])[:2]
    within = "within" if g_near <= spread else "outside"
    return (
        f"{name}: under the '{near}' reading ours differs from the paper's by {g_near:.3g} "
        f"on average over {n} cells, {within} the paper's own spread over its cells "
        f"(±{spread:.3g}); under the '{far}' reading by {g_far:.3g}, {g_far - g_near:.3g} "
        f"further."
    )


def t_local(records: pd.DataFrame) -> pd.DataFrame:
    """T-local (paper Tables 3–4): object occlusions by m × overlapping × κ × α (and by
    ``model`` when the records have one)."""
    records = _readings(records)
    by = _by_model(records, ["m", "overlapping", "kappa", "alpha"])
    out = summarise(_kind(records, ("objects",)), by)
    return _with_paper(
        out, PAPER_T_LOCAL, lambda r: (int(r.m), bool(r.overlapping), r.kappa, r.alpha)
    )


def t_global(records: pd.DataFrame) -> pd.DataFrame:
    """T-global (paper Tables 5–6): contrast c and brightness b by level × κ × α (and by
    ``model`` when the records have one), with the mean clipped-pixel fraction of each
    cell's hulls."""
    records = _readings(_kind(records, ("contrast", "brightness")))
    by = _by_model(records, ["kind", "level", "kappa", "alpha"])
    out = summarise(records, by)
    if "clipped_fraction" in records:
        clipped = records.groupby(by, sort=True, dropna=False)["clipped_fraction"].mean()
        out.insert(len(by), "clipped_fraction", clipped.to_numpy())
    return _with_paper(out, PAPER_T_GLOBAL, lambda r: (r.kind, _level(r.level), r.kappa, r.alpha))


def t_resnet(records: pd.DataFrame) -> pd.DataFrame:
    """T-resnet (paper §8.4): ResNet-18 block occlusions by overlapping (κ = 1, α = 1.5)."""
    records = _readings(_kind(records, ("blocks",)))
    out = summarise(records, _by_model(records, ["overlapping", "kappa", "alpha"]))
    return _with_paper(
        out,
        {(o, 1.0, 1.5): v for o, v in PAPER_T_RESNET.items()},
        lambda r: (bool(r.overlapping), r.kappa, r.alpha),
    )


def _kind(records: pd.DataFrame, kinds: tuple[str, ...]) -> pd.DataFrame:
    if "kind" not in records:
        raise ValueError("records: expected campaign records with a 'kind' column")
    return records[records["kind"].isin(kinds)]


def _level(level: float) -> float:
    """The paper's level nearest ``level`` (stored levels are floats)."""
    known = (5e-4, 5e-3, 1e-2, 1.0, 2.0)
    return next((k for k in known if np.isclose(level, k, rtol=1e-6, atol=0)), float(level))


def _with_paper(out: pd.DataFrame, paper: dict, key) -> pd.DataFrame:
    values = [paper.get(key(r), (np.nan,) * 3) for r in out.itertuples(index=False)]
    out["paper_rate"] = [v[2] for v in values]
    out["paper_rate_lo"], out["paper_rate_hi"] = paper_interval(out["paper_rate"])
    out["paper_time_mean"] = [v[0] for v in values]
    out["paper_time_std"] = [v[1] for v in values]
    return out


#: The node counts at which :func:`decided_by_nodes` reads how much a run had decided.
NODE_MARKS = (0, 1, 4, 16, 64, 256, 1024, 4096)
#: Per method of the records, its verdict and node count columns.
_SEARCHES = (("alloc", "status", "nodes"), ("pb", "pb_status", "pb_nodes"))


def decided_by_nodes(records: pd.DataFrame) -> pd.DataFrame:
    """How much of a verification table each search had decided by a given node count.

    For each model, reading and method (``alloc``: ``status``/``nodes``; ``pb``:
    ``pb_status``/``pb_nodes``), the share of its instances decided (``holds`` or
    ``violated``) within ``≤ N`` nodes, for each ``N`` of :data:`NODE_MARKS` up to the
    first that covers the most nodes any of them used. It reads this run's searches as
    they went: what a smaller node budget would have decided at least (the search is the
    same up to the budget; ``pose_bound_refine_nodes`` could add more), what a larger one
    gained.

    Returns
    -------
    DataFrame
        ``model``, ``tolerance_units``, ``method``, ``instances``, ``decided`` (the share at
        the run's own budgets) and one column ``≤ N`` per mark: shares in [0, 1]. No row for
        a method without records (``pb`` under a reading that did not run it) or without
        node counts (records from before they were stored, errors only).

    Examples
    --------
    >>> records = pd.DataFrame({"model": "cnn", "tolerance_units": "heatmap",
    ...                         "status": ["holds", "violated", "unknown", "holds"],
    ...                         "nodes": [3, 0, 16, 16]})
    >>> decided_by_nodes(records).iloc[0].to_dict()  # doctest: +NORMALIZE_WHITESPACE
    {'model': 'cnn', 'tolerance_units': 'heatmap', 'method': 'alloc', 'instances': 4,
     'decided': 0.75, '≤ 0': 0.25, '≤ 1': 0.25, '≤ 4': 0.5, '≤ 16': 0.75}
    """
    rows = []
    for (model, units), part in records.groupby(["model", "tolerance_units"], sort=False):
        for method, status, nodes in _SEARCHES:
            if status not in part or nodes not in part:
                continue
            ran = part[part[status].isin(["holds", "violated", "unknown"])]
            used = pd.to_numeric(ran[nodes], errors="coerce")
            if ran.empty or used.isna().all():
                continue
            decided = ran[status].isin(["holds", "violated"]).to_numpy()
            row = dict(
                model=model,
                tolerance_units=units,
                method=method,
                instances=len(ran),
                decided=float(decided.mean()),
            )
            most = used.max()
            for mark in NODE_MARKS:
                row[f"≤ {mark}"] = float((decided & (used <= mark).to_numpy()).mean())
                if mark >= most:
                    break
            rows.append(row)
    return pd.DataFrame(rows)


def pose_bound_ratios(records: pd.DataFrame, column: str = "pb_bound") -> pd.DataFrame:
    """A pose-bound quantity ÷ ε at α = 1 (``[10°, 10°, 10°, 4, 4, 20 m]``) per pose axis,
    one row per hull (it does not depend on α or κ).

    ``column``: ``'pb_bound'``, the linearised bound ``max |M δ|`` over the regions
    (records whose search stopped at a violated seed have none and are left out), or
    ``'pb_exact'``, the largest PnP pose error over every combination of region pixels
    (certified: exact for argmax → PnP over the regions; only hulls whose combinations
    were enumerated, ``inf`` where some pose is not valid). Columns: the hull's fields and
    ``roll, pitch, yaw, tx, ty, tz``.
    """
    if column not in ("pb_bound", "pb_exact"):
        raise ValueError(f"column: expected 'pb_bound' or 'pb_exact', got {column!r}")
    fields = ("model", "kind", "image_id", "m", "overlapping", "level")
    hull = [c for c in fields if c in records]
    if column not in records:  # records from before the enumeration: no exact errors
        return pd.DataFrame(columns=[*hull, *POSE_AXES])
    rows = records.dropna(subset=[column]).drop_duplicates(hull)
    values = np.array([_list(b) for b in rows[column]], dtype=np.float64)
    out = pd.DataFrame(values.reshape(-1, 6) / tolerance(1.0), columns=POSE_AXES)
    return pd.concat([rows[hull].reset_index(drop=True), out], axis=1)


def plot_pose_bounds(records: pd.DataFrame, title: str):
    """Distribution of the linearised bound ÷ ε per pose axis (log scale), one point per
    hull, and beside it, where the hull's combinations were enumerated, the certified
    (exact) PnP error ÷ ε: below 1 is inside Ξ at α = 1, below 1.5 at α = 1.5; an
    infinite error (a pose PnP flags as not valid) is a triangle at the top edge. Returns
    a matplotlib figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    linearised = pose_bound_ratios(records, "pb_bound")
    exact = pose_bound_ratios(records, "pb_exact")
    fig, ax = plt.subplots(figsize=(6.5, 4), layout="constrained")
    rng = np.random.default_rng(0)
    finite = np.concatenate([linearised[list(POSE_AXES)].to_numpy(np.float64).ravel(), [1.5]])
    finite = np.concatenate([finite, exact[list(POSE_AXES)].to_numpy(np.float64).ravel()])
    finite = finite[np.isfinite(finite) & (finite > 0)]
    top = 2.0 * finite.max()
    series = (
        (linearised, -0.2, "C0", "linearised bound"),
        (exact, 0.2, "C2", "certified: PnP over every region combination"),
    )
    for ratios, shift, color, label in series:
        if not len(ratios):
            continue
        jitter = rng.uniform(-0.12, 0.12, len(ratios))
        for i, a in enumerate(POSE_AXES):  # one point per hull: often bimodal
            y = ratios[a].to_numpy(np.float64)
            off = np.isinf(y)  # a pose PnP flags as not valid: outside Ξ, drawn at the top
            x = i + shift + jitter
            ax.scatter(x[~off], y[~off], s=12, alpha=0.6, color=color, label=label)
            ax.scatter(x[off], np.full(off.sum(), top), s=18, marker="^", color=color)
            y = np.where(off, top, y)
            ax.hlines(np.median(y), i + shift - 0.15, i + shift + 0.15, color="C1", lw=2)
            label = None
    ax.set_xticks(range(6), POSE_AXES)
    for level, style in ((1.0, "--"), (1.5, ":")):
        ax.axhline(level, color="k", ls=style, lw=0.8, label=f"inside Ξ at α = {level:g}")
    ax.set_yscale("log")
    ax.set_ylabel("pose error ÷ ε (α = 1)")
    ax.set_title(
        f"{title}\nlinearised bound: {len(linearised)} hulls, certified (enumerated): "
        f"{len(exact)}; medians in orange",
        fontsize="medium",
    )
    ax.legend(fontsize="small")
    return fig
