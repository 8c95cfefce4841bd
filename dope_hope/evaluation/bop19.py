"""BOP19 average recall (localization task), as the BOP toolkit computes it.

Targets from ``test_targets_bop19.json`` when the dataset has one, else every (image, object)
with GT instances of visibility >= 0.1 (inst_count = their number; a missing visibility counts
as visible); for each target only the ``inst_count`` top-scoring estimates are evaluated and
the ``inst_count`` most visible GT instances are the valid ones; greedy matching. A pose is
correct when its error is strictly below the threshold. AR_MSSD: thresholds 0.05 .. 0.5 of the
diameter, the error is infinite when ``|t_e - t_g| >= diameter`` (the toolkit's short-cut);
AR_MSPD: 5 .. 50 px scaled by 640 / image width; AR_VSD: delta 15 mm, tau 0.05 .. 0.5 of the
diameter, thresholds 0.05 .. 0.5 (VSD is 1 when the projections of the bounding spheres do not
overlap; needs test depth and meshes, skipped and reported so when a frame has no depth);
AR = mean of the three. Recall = true positives / valid GT instances, over all targets.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.evaluation import metrics
from dope_hope.evaluation.datasets import VISIB_GT_MIN, Dataset
from dope_hope.evaluation.matching import greedy_match
from dope_hope.evaluation.models import ObjectModel
from dope_hope.io.predictions import Prediction

BOP19_MSSD_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))   # x diameter


BOP19_MSPD_THRESHOLDS = tuple(5.0 * k for k in range(1, 11))              # px at width 640


BOP19_VSD_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))


# =========================================================================== BOP19
@dataclass
class BopTarget:
    """One (image, object) target with the errors of its estimates.

    Attributes:
        inst_count: number of instances to find (BOP ``inst_count``).
        scores: (E,) estimate scores.
        visibility: (G,) GT visible fractions (all GT instances of the object in the image).
        errors: error type -> (E, G) ("mssd" normalized by the diameter, "mspd" in px at
            width 640) or (E, G, T) for "vsd" (one slice per tau).
    """

    inst_count: int
    scores: np.ndarray
    visibility: np.ndarray
    errors: dict[str, np.ndarray]


def _top_estimates(scores: np.ndarray, inst_count: int) -> np.ndarray:
    """Indices of the ``inst_count`` top-scoring estimates (descending; ties: file order)."""
    return np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")[:inst_count]


def _valid_gt(visibility: np.ndarray, inst_count: int) -> np.ndarray:
    """(G,) bool: the ``inst_count`` most visible GT instances (BOP with visib_gt_min = -1)."""
    valid = np.zeros(len(visibility), dtype=bool)
    valid[np.argsort(-np.asarray(visibility, dtype=np.float64), kind="stable")[:inst_count]] = True
    return valid


def bop_recalls(targets: list[BopTarget], error_type: str,
                thresholds: Sequence[float]) -> np.ndarray:
    """BOP19 recall per threshold (per tau x threshold for "vsd").

    Only the ``inst_count`` top-scoring estimates of each target are evaluated, only the
    ``inst_count`` most visible GT instances can be matched and are counted; matching is
    :func:`greedy_match` (strict ``error < threshold``). Recall = true positives / valid GT.

    Returns:
        (len(thresholds),), or (T, len(thresholds)) for "vsd".
    """
    n_taus = None
    tp = None
    total = 0
    for tg in targets:
        top = _top_estimates(tg.scores, tg.inst_count)
        valid = _valid_gt(tg.visibility, tg.inst_count)
        total += int(valid.sum())
        E = np.asarray(tg.errors[error_type], dtype=np.float64)
        if E.ndim == 2:
            E = E[:, :, None]
        if tp is None:
            n_taus = E.shape[2]
            tp = np.zeros((n_taus, len(thresholds)))
        if len(top) == 0 or E.shape[1] == 0:
            continue
        for k in range(n_taus):
            for j, th in enumerate(thresholds):
                m = greedy_match(E[top, :, k], tg.scores[top], th, valid)
                tp[k, j] += np.count_nonzero(m >= 0)
    if tp is None:
        shape = (len(thresholds),) if error_type != "vsd" else (len(metrics.BOP19_VSD_TAUS), len(thresholds))
        return np.zeros(shape)
    rec = tp / total if total else np.zeros_like(tp)
    return rec if error_type == "vsd" else rec[0]


def bop_mssd_error(R_e, t_e, R_g, t_g, model: ObjectModel) -> float:
    """MSSD / diameter with the BOP toolkit's short-cut: inf when ``|t_e - t_g| >= diameter``."""
    if metrics.te(t_e, t_g) >= model.diameter:
        return math.inf
    return metrics.mssd(R_e, t_e, R_g, t_g, model.points, model.symmetries) / model.diameter


def bop_mspd_error(R_e, t_e, R_g, t_g, K, width: int, model: ObjectModel) -> float:
    """MSPD in pixels scaled to an image width of 640 (no short-cut, as in the toolkit)."""
    return metrics.mspd(R_e, t_e, R_g, t_g, K, model.points, model.symmetries) * 640.0 / width


def bop_vsd_errors(R_e, t_e, R_g, t_g, depth, K, model: ObjectModel,
                   renderer: metrics.DepthRenderer | None = None) -> np.ndarray:
    """BOP19 VSD errors (one per tau); all 1 when the bounding-sphere projections are apart."""
    if not metrics.sphere_projections_overlap(0.5 * model.diameter, t_e, t_g):
        return np.ones(len(metrics.BOP19_VSD_TAUS))
    return metrics.vsd(R_e, t_e, R_g, t_g, depth, K, model.mesh, diameter=model.diameter,
                       renderer=renderer)


def bop_targets_from_gt(dataset: Dataset) -> tuple[dict[tuple[int, str], int], bool]:
    """{(frame index, class): inst_count} of GT instances with visibility >= 0.1.

    Returns:
        (targets, visibility_missing): the flag tells whether some GT had no visibility (they
        count as visible).
    """
    out: dict[tuple[int, str], int] = {}
    missing = False
    for fi, f in enumerate(dataset.frames):
        for o in f.objects:
            vis = o.visibility
            if vis is None:
                missing = True
                vis = 1.0
            if vis >= VISIB_GT_MIN:
                out[(fi, o.class_name)] = out.get((fi, o.class_name), 0) + 1
    return out, missing


def bop19_average_recall(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                         models: dict[str, ObjectModel], use_vsd: bool | None = None,
                         progress: bool = False) -> dict[str, Any]:
    """BOP19 AR_VSD, AR_MSSD, AR_MSPD and AR (see the module docstring).

    Args:
        use_vsd: compute AR_VSD (None: when every frame with targets has depth and K).

    Returns:
        {"ar", "ar_vsd" (None when skipped), "ar_mssd", "ar_mspd", "recalls": {...},
        "targets", "gt_valid", "notes": [...]}.
    """
    from tqdm import tqdm

    notes = []
    if dataset.targets is not None:
        targets = {}
        for fi, f in enumerate(dataset.frames):
            for o in {o.class_name for o in f.objects}:
                oid = models[o].obj_id
                key = (f.scene_id, f.im_id, oid)
                if key in dataset.targets:
                    targets[(fi, o)] = dataset.targets[key]
        notes.append(f"targets: test_targets_bop19.json ({len(targets)} image-object targets)")
    else:
        targets, missing = bop_targets_from_gt(dataset)
        notes.append(f"targets: all GT instances with visibility >= {VISIB_GT_MIN} "
                     f"({len(targets)} image-object targets)")
        if missing:
            notes.append("some GT instances have no visibility: counted as visible")
    frames_used = sorted({fi for fi, _ in targets})
    if use_vsd is None:
        use_vsd = all(dataset.frames[fi].depth_path is not None and dataset.frames[fi].K is not None
                      for fi in frames_used)
        if not use_vsd:
            notes.append("AR_VSD skipped: not every test image has a depth image "
                         "(AR is the mean of AR_MSSD and AR_MSPD only)")
    for fi in frames_used:
        f = dataset.frames[fi]
        if f.K is None or not f.width:
            raise InputFileError(f.key, "BOP AR needs the camera intrinsics and the image width")
    procedural = sorted(n for n, m in models.items() if m.procedural)
    if procedural:
        notes.append("procedural cuboid models (no mesh) for: " + ", ".join(procedural))
    renderer = metrics.default_renderer() if use_vsd else None
    from dope_hope.io.images import read_depth_m

    per_frame: dict[int, list[tuple[str, int]]] = {}
    for (fi, cls), count in sorted(targets.items()):
        per_frame.setdefault(fi, []).append((cls, count))
    bop_targets: list[BopTarget] = []
    for fi in tqdm(frames_used, desc="BOP errors", unit="img", disable=not progress):
        f = dataset.frames[fi]
        depth = read_depth_m(f.depth_path, f.depth_scale_m) if use_vsd else None
        for cls, count in per_frame[fi]:
            model = models[cls]
            gts = [o for o in f.objects if o.class_name == cls]
            ests = [p for p in preds_by_frame[fi] if p.class_name == cls]
            scores = np.array([p.score for p in ests], dtype=np.float64)
            top = _top_estimates(scores, count)
            ests = [ests[i] for i in top]
            E, G = len(ests), len(gts)
            errs = {"mssd": np.empty((E, G)), "mspd": np.empty((E, G))}
            if use_vsd:
                errs["vsd"] = np.empty((E, G, len(metrics.BOP19_VSD_TAUS)))
            for i, p in enumerate(ests):
                for j, g in enumerate(gts):
                    errs["mssd"][i, j] = bop_mssd_error(p.R, p.t, g.R, g.t, model)
                    errs["mspd"][i, j] = bop_mspd_error(p.R, p.t, g.R, g.t, f.K, f.width, model)
                    if use_vsd:
                        errs["vsd"][i, j] = bop_vsd_errors(p.R, p.t, g.R, g.t, depth, f.K, model,
                                                           renderer)
            vis = np.array([1.0 if o.visibility is None else o.visibility for o in gts])
            bop_targets.append(BopTarget(count, scores[top], vis, errs))
    rec_mssd = bop_recalls(bop_targets, "mssd", BOP19_MSSD_THRESHOLDS)
    rec_mspd = bop_recalls(bop_targets, "mspd", BOP19_MSPD_THRESHOLDS)
    out: dict[str, Any] = {"ar_mssd": float(rec_mssd.mean()), "ar_mspd": float(rec_mspd.mean()),
                           "recalls": {"mssd": rec_mssd.tolist(), "mspd": rec_mspd.tolist()},
                           "targets": len(targets),
                           "gt_valid": int(sum(_valid_gt(t.visibility, t.inst_count).sum()
                                               for t in bop_targets))}
    if use_vsd:
        rec_vsd = bop_recalls(bop_targets, "vsd", BOP19_VSD_THRESHOLDS)
        out["ar_vsd"] = float(rec_vsd.mean())
        out["recalls"]["vsd"] = rec_vsd.tolist()
        out["ar"] = float(np.mean([out["ar_vsd"], out["ar_mssd"], out["ar_mspd"]]))
    else:
        out["ar_vsd"] = None
        out["ar"] = float(np.mean([out["ar_mssd"], out["ar_mspd"]]))
    out["notes"] = notes
    return out
