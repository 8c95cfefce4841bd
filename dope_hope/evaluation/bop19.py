"""BOP19 average recall (localization task) as the BOP toolkit's ``eval_bop19_pose.py`` computes
it, with its arithmetic (millimetres, the poses as stored in ``scene_gt.json`` and the CSV
(``stored_pose``; ``1000 t`` for other inputs), every vertex of the model file (``BopModel``),
``models_info`` diameter and symmetries): targets from ``test_targets_bop19.json`` when the
dataset has one, else every (image, object) with GT instances of visibility >= 0.1 (inst_count
= their number; a missing visibility counts as visible); estimates that are not of a target are
ignored; for each target only the ``inst_count`` top-scoring estimates are evaluated and the
``inst_count`` most visible GT instances are the valid ones; greedy matching
(:func:`dope_hope.evaluation.matching.greedy_match`), redone per threshold. A pose is correct
when its error is strictly below the threshold; thresholds ``np.arange(0.05, 0.51, 0.05)``
exactly (0.15000000000000002, ...). AR_MSSD: MSSD / diameter, infinite unless ``|t_e - t_g| <
diameter`` (the toolkit's short-cut); AR_MSPD: ``(640 / width) * MSPD`` against 5 .. 50 px,
width 1920 for HOPE (the toolkit's dataset constant, not the image files); AR_VSD: delta 15 mm,
taus as the thresholds, normalized by the diameter, depth rendered as the toolkit's renderer
(:mod:`dope_hope.render.depth`; VSD is 1 when the projections of the bounding spheres do not
overlap; needs test depth and a triangle mesh, skipped and reported so otherwise); AR = mean of
the three. Recall = true positives / valid GT instances, over all targets.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from dope_hope.annotation import ObjectAnnotation
from dope_hope.errors import InputFileError
from dope_hope.evaluation import metrics
from dope_hope.evaluation.datasets import VISIB_GT_MIN, Dataset, EvalFrame
from dope_hope.evaluation.matching import greedy_match
from dope_hope.evaluation.object_models import BopModel, ObjectModel
from dope_hope.io.images import read_depth_m, read_image_raw
from dope_hope.io.predictions import Prediction

# Thresholds exactly as the toolkit's eval_bop19_pose.py builds them (np.arange: the third is
# 0.15000000000000002, so an error of exactly 0.15 is correct there).
BOP19_MSSD_THRESHOLDS = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))  # x diameter
BOP19_MSPD_THRESHOLDS = tuple(float(x) for x in np.arange(5, 51, 5))          # px at width 640
BOP19_VSD_THRESHOLDS = BOP19_MSSD_THRESHOLDS


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
        key: (scene_id, im_id, obj_id) when known.
        est_ids: (E,) the toolkit's ``est_id`` of each estimate (its index among the
            (scene, image, object) rows in file order), when known.
        gt_ids: (G,) the toolkit's ``gt_id`` of each GT instance (its index in the image's
            ``scene_gt.json`` list), when known.
    """

    inst_count: int
    scores: np.ndarray
    visibility: np.ndarray
    errors: dict[str, np.ndarray]
    key: tuple[int, int, int] | None = None
    est_ids: np.ndarray | None = None
    gt_ids: np.ndarray | None = None


def _top_estimates(scores: np.ndarray, inst_count: int) -> np.ndarray:
    """Indices of the ``inst_count`` top-scoring estimates (descending; ties: file order)."""
    return np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")[:inst_count]


def _valid_gt(visibility: np.ndarray, inst_count: int) -> np.ndarray:
    """(G,) bool: the ``inst_count`` most visible GT instances (BOP with visib_gt_min = -1)."""
    valid = np.zeros(len(visibility), dtype=bool)
    valid[np.argsort(-np.asarray(visibility, dtype=np.float64), kind="stable")[:inst_count]] = True
    return valid


def target_matches(tg: BopTarget, error_type: str, thresholds: Sequence[float]) -> np.ndarray:
    """The toolkit's matching of one target, redone per threshold (and per tau for "vsd").

    Only the ``inst_count`` top-scoring estimates are evaluated, only the ``inst_count`` most
    visible GT instances can be matched; matching is :func:`greedy_match` (strict ``error <
    threshold``).

    Returns:
        (T, len(thresholds), E) int: the GT index (into ``tg.visibility``) each estimate is
        matched to, -1 for none (estimates outside the top ``inst_count``: -1); T = 1 unless
        "vsd".
    """
    E = np.asarray(tg.errors[error_type], dtype=np.float64)
    if E.ndim == 2:
        E = E[:, :, None]
    out = np.full((E.shape[2], len(thresholds), E.shape[0]), -1, dtype=np.int64)
    top = _top_estimates(tg.scores, tg.inst_count)
    if len(top) == 0 or E.shape[1] == 0:
        return out
    valid = _valid_gt(tg.visibility, tg.inst_count)
    for k in range(E.shape[2]):
        for j, th in enumerate(thresholds):
            out[k, j, top] = greedy_match(E[top, :, k], tg.scores[top], th, valid)
    return out


def bop_recalls(targets: list[BopTarget], error_type: str,
                thresholds: Sequence[float]) -> np.ndarray:
    """BOP19 recall per threshold (per tau x threshold for "vsd"): true positives
    (:func:`target_matches`) / valid GT instances (the ``inst_count`` most visible of each
    target), over all targets.

    Returns:
        (len(thresholds),), or (T, len(thresholds)) for "vsd".
    """
    tp = None
    total = 0
    for tg in targets:
        total += int(_valid_gt(tg.visibility, tg.inst_count).sum())
        counts = (target_matches(tg, error_type, thresholds) >= 0).sum(axis=2)
        tp = counts if tp is None else tp + counts
    if tp is None:
        shape = (len(thresholds),) if error_type != "vsd" else (len(metrics.BOP19_VSD_TAUS), len(thresholds))
        return np.zeros(shape)
    rec = tp / float(total) if total else np.zeros(tp.shape)
    return rec if error_type == "vsd" else rec[0]


def bop_pose_mm(x: ObjectAnnotation | Prediction) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,) mm) of a GT instance or an estimate as the BOP toolkit sees it: the
    numbers of the BOP file when it came from one (``stored_pose``), else ``(R, 1000 t)`` (what
    ``write_bop_csv`` writes)."""
    if x.stored_pose is not None:
        return x.stored_pose
    return np.asarray(x.R, dtype=np.float64), 1000.0 * np.asarray(x.t, dtype=np.float64)


def bop_mssd_mm(R_e, t_e, R_g, t_g, model: BopModel) -> float:
    """MSSD in mm as the toolkit's eval_calc_errors computes it (poses in mm): infinite
    unless ``|t_e - t_g| < diameter`` (its short-cut)."""
    center_dist = np.linalg.norm(np.asarray(t_e, np.float64).reshape(3)
                                 - np.asarray(t_g, np.float64).reshape(3))
    if not center_dist < model.diameter:
        return math.inf
    return metrics.mssd(R_e, t_e, R_g, t_g, model.points, model.symmetries)


def bop_mssd_error(R_e, t_e, R_g, t_g, model: BopModel) -> float:
    """MSSD / diameter as the toolkit scores it: ``bop_mssd_mm(...) / float(diameter)``."""
    return bop_mssd_mm(R_e, t_e, R_g, t_g, model) / float(model.diameter)


def bop_mspd_error(R_e, t_e, R_g, t_g, K, width: int, model: BopModel) -> float:
    """MSPD in pixels scaled to an image width of 640 as the toolkit scores it:
    ``(640.0 / width) * mspd`` (poses in mm; no short-cut)."""
    return _mspd_factor(width) * metrics.mspd(R_e, t_e, R_g, t_g, K, model.points, model.symmetries)


def _mspd_factor(width: int) -> float:
    return 640.0 / width


def bop_vsd_errors(R_e, t_e, R_g, t_g, depth_mm, K, model: BopModel,
                   renderer: Any = None) -> list[float]:
    """BOP19 VSD errors (one per tau; poses and depth in mm, delta 15 mm): all 1.0 when the
    projections of the bounding spheres (radius = diameter / 2) do not overlap."""
    radius = 0.5 * model.diameter
    if not metrics.sphere_projections_overlap(radius, t_e, t_g):
        return [1.0] * len(metrics.BOP19_VSD_TAUS)
    return metrics.vsd(R_e, t_e, R_g, t_g, depth_mm, K, (model.points, model.faces),
                       delta=metrics.BOP19_VSD_DELTA_MM, diameter=model.diameter,
                       renderer=renderer)


#: Image size (width, height) of the BOP datasets this package evaluates, as the toolkit's
#: ``dataset_params`` gives it; MSPD is scaled by 640 / width.
BOP_DATASET_IMAGE_SIZE = {"hope": (1920, 1080), "hopev2": (1920, 1080)}


def _bop_depth_mm(frame: EvalFrame) -> np.ndarray:
    """(H, W) float32 test depth in mm, as the toolkit loads it (``load_depth`` as float32,
    times the scene's ``depth_scale`` in float32)."""
    img = read_image_raw(frame.depth_path)
    if img.ndim == 3:
        img = img[:, :, 0]
    if np.issubdtype(img.dtype, np.integer):
        return img.astype(np.float32) * np.float32(frame.depth_scale_m / 0.001)
    return read_depth_m(frame.depth_path) * np.float32(1000.0)


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


def _select_targets(dataset: Dataset, models: dict[str, ObjectModel],
                    notes: list[str]) -> dict[tuple[int, str], int]:
    """{(frame index, class): inst_count}: the dataset's ``test_targets_bop19.json`` entries,
    else every GT instance visible enough (the toolkit's rule); says which in ``notes``."""
    if dataset.targets is not None:
        targets = {}
        for fi, f in enumerate(dataset.frames):
            for o in {o.class_name for o in f.objects}:
                oid = models[o].obj_id
                key = (f.scene_id, f.im_id, oid)
                if key in dataset.targets:
                    targets[(fi, o)] = dataset.targets[key]
        notes.append(f"targets: test_targets_bop19.json ({len(targets)} image-object targets)")
        return targets
    targets, missing = bop_targets_from_gt(dataset)
    notes.append(f"targets: all GT instances with visibility >= {VISIB_GT_MIN} "
                 f"({len(targets)} image-object targets)")
    if missing:
        notes.append("some GT instances have no visibility: counted as visible")
    return targets


def _check_inputs(dataset: Dataset, preds_by_frame: list[list[Prediction]], models: dict[str, ObjectModel],
                  targets: dict[tuple[int, str], int], use_vsd: bool | None,
                  notes: list[str]) -> tuple[bool, tuple[int, int] | None]:
    """Whether VSD is computed (``use_vsd`` None: when every target image has depth and every
    model triangles) and the dataset's image size for MSPD (None: each image's width); what
    differs from the toolkit's inputs goes to ``notes``.

    Raises:
        InputFileError: a target image without K or width.
    """
    n_est = sum(len(p) for p in preds_by_frame)
    n_target_est = sum(1 for fi, ps in enumerate(preds_by_frame) for p in ps
                       if (fi, p.class_name) in targets)
    if n_est > n_target_est:
        notes.append(f"{n_est - n_target_est} of {n_est} estimates are not of a target "
                     f"(image, object): ignored, as the toolkit ignores them")
    frames_used = sorted({fi for fi, _ in targets})
    classes_used = sorted({c for _, c in targets})
    if use_vsd is None:
        use_vsd = all(dataset.frames[fi].depth_path is not None and dataset.frames[fi].K is not None
                      for fi in frames_used)
        if not use_vsd:
            notes.append("AR_VSD skipped: not every test image has a depth image "
                         "(AR is the mean of AR_MSSD and AR_MSPD only)")
        elif any(models[c].bop.faces is None for c in classes_used):
            use_vsd = False
            notes.append("AR_VSD skipped: a model is a point cloud (no triangles to render)")
    image_size = BOP_DATASET_IMAGE_SIZE.get(dataset.name or "") if dataset.fmt == "bop" else None
    if image_size is not None:
        notes.append(f"MSPD image width: {image_size[0]} px ({dataset.name}, as the toolkit's "
                     f"dataset_params)")
    for fi in frames_used:
        f = dataset.frames[fi]
        if f.K is None or not (image_size or f.width):
            raise InputFileError(f.key, "BOP AR needs the camera intrinsics and the image width "
                                        "(an image file, or a BOP dataset named hope / hopev2)")
    inexact = sorted(c for c in classes_used if not models[c].bop.exact)
    if inexact:
        notes.append("not the toolkit's inputs (a BOP obj_XXXXXX.ply + models_info.json in mm) "
                     "for: " + ", ".join(inexact))
    elsewhere = sorted(c for c in classes_used if models[c].bop.exact
                       and models[c].bop.path.parent.name != "models_eval")
    if dataset.fmt == "bop" and elsewhere:
        notes.append("the toolkit scores BOP19 with DATASET/models_eval/; not from a models_eval "
                     "folder: " + ", ".join(f"{c} ({models[c].bop.path})" for c in elsewhere))
    procedural = sorted(n for n, m in models.items() if m.procedural)
    if procedural:
        notes.append("procedural cuboid models (no mesh) for: " + ", ".join(procedural))
    return bool(use_vsd), image_size


@dataclass
class _FrameInputs:
    """What one target image's errors need: the frame, its predictions, the MSPD width, the
    depth (mm) when VSD is computed, the renderer and where to put the details (or None)."""

    frame: EvalFrame
    preds: list[Prediction]
    width: int
    depth: np.ndarray | None
    renderer: Any
    pairs: list[dict[str, Any]] | None


def _target_errors(inp: _FrameInputs, obj: ObjectModel, cls: str, count: int) -> BopTarget:
    """The errors of one (image, object) target: its ``count`` top-scoring estimates (file order
    among equals) against every GT instance of the class, in the toolkit's units."""
    f, model, use_vsd = inp.frame, obj.bop, inp.depth is not None
    gt_objs = [o for o in f.objects if o.class_name == cls]
    gts = [bop_pose_mm(o) for o in gt_objs]
    ests = [p for p in inp.preds if p.class_name == cls]  # file order
    scores = np.array([p.score for p in ests], dtype=np.float64)
    top = _top_estimates(scores, count)
    est_poses = [bop_pose_mm(ests[i]) for i in top]
    E, G = len(est_poses), len(gts)
    errs = {"mssd": np.empty((E, G)), "mspd": np.empty((E, G))}
    if use_vsd:
        errs["vsd"] = np.empty((E, G, len(metrics.BOP19_VSD_TAUS)))
    key = (f.scene_id, f.im_id, obj.obj_id)
    gt_ids = np.array([o.instance_id for o in gt_objs])
    for i, (R_e, t_e) in enumerate(est_poses):
        for j, (R_g, t_g) in enumerate(gts):
            mssd_mm = bop_mssd_mm(R_e, t_e, R_g, t_g, model)
            mspd_px = metrics.mspd(R_e, t_e, R_g, t_g, f.K, model.points, model.symmetries)
            errs["mssd"][i, j] = mssd_mm / float(model.diameter)
            errs["mspd"][i, j] = _mspd_factor(inp.width) * mspd_px
            if use_vsd:
                errs["vsd"][i, j] = bop_vsd_errors(R_e, t_e, R_g, t_g, inp.depth, f.K, model, inp.renderer)
            if inp.pairs is not None:
                inp.pairs.append({"scene_id": key[0], "im_id": key[1], "obj_id": key[2],
                                  "est_id": int(top[i]), "gt_id": int(gt_ids[j]),
                                  "mssd": mssd_mm, "mspd": mspd_px,
                                  "vsd": errs["vsd"][i, j].tolist() if use_vsd else None})
    vis = np.array([1.0 if o.visibility is None else o.visibility for o in gt_objs])
    return BopTarget(count, scores[top], vis, errs, key, top, gt_ids)


def _average_recalls(bop_targets: list[BopTarget], n_targets: int, use_vsd: bool) -> dict[str, Any]:
    """AR_MSSD, AR_MSPD, AR_VSD (None when skipped) and AR as eval_bop19_pose.py averages them."""
    rec_mssd = bop_recalls(bop_targets, "mssd", BOP19_MSSD_THRESHOLDS)
    rec_mspd = bop_recalls(bop_targets, "mspd", BOP19_MSPD_THRESHOLDS)
    # AR = np.mean over the list of recalls, as eval_bop19_pose.py averages them
    out: dict[str, Any] = {"ar_mssd": float(np.mean(list(rec_mssd))),
                           "ar_mspd": float(np.mean(list(rec_mspd))),
                           "recalls": {"mssd": rec_mssd.tolist(), "mspd": rec_mspd.tolist()},
                           "targets": n_targets,
                           "gt_valid": int(sum(_valid_gt(t.visibility, t.inst_count).sum()
                                               for t in bop_targets))}
    if use_vsd:
        rec_vsd = bop_recalls(bop_targets, "vsd", BOP19_VSD_THRESHOLDS)
        out["ar_vsd"] = float(np.mean(list(rec_vsd.ravel())))  # tau outer, threshold inner
        out["recalls"]["vsd"] = rec_vsd.tolist()
        out["ar"] = float(np.mean([out["ar_vsd"], out["ar_mssd"], out["ar_mspd"]]))
    else:
        out["ar_vsd"] = None
        out["ar"] = float(np.mean([out["ar_mssd"], out["ar_mspd"]]))
    return out


def bop19_average_recall(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                         models: dict[str, ObjectModel], use_vsd: bool | None = None,
                         progress: bool = False, renderer: Any = None,
                         details: bool = False) -> dict[str, Any]:
    """BOP19 AR_VSD, AR_MSSD, AR_MSPD and AR, as the BOP toolkit computes them.

    Errors are computed in the toolkit's units and operations (mm, every model vertex, the
    stored poses, thresholds ``np.arange``); see the module docstring.

    Args:
        use_vsd: compute AR_VSD (None: when every frame with targets has depth and K and
            every model has triangles).
        renderer: for VSD (default: the shared :class:`dope_hope.render.depth.DepthRenderer`).
        details: also return ``"details"``: ``"pairs"`` (one record per evaluated (estimate,
            GT) pair with the toolkit's ``est_id`` / ``gt_id`` and its raw errors: MSSD mm,
            MSPD px, VSD per tau) and ``"matches"`` (:func:`_match_details`), for comparing
            with the toolkit's ``errors_*.json`` / ``matches_*.json``.

    Returns:
        {"ar", "ar_vsd" (None when skipped), "ar_mssd", "ar_mspd", "recalls": {...},
        "targets", "gt_valid", "notes": [...]}.
    """
    notes: list[str] = []
    targets = _select_targets(dataset, models, notes)
    use_vsd, image_size = _check_inputs(dataset, preds_by_frame, models, targets, use_vsd, notes)
    per_frame: dict[int, list[tuple[str, int]]] = {}
    for (fi, cls), count in sorted(targets.items()):
        per_frame.setdefault(fi, []).append((cls, count))
    bop_targets: list[BopTarget] = []
    pairs: list[dict[str, Any]] = []
    for fi in tqdm(sorted({fi for fi, _ in targets}), desc="BOP errors", unit="img", disable=not progress):
        f = dataset.frames[fi]
        inp = _FrameInputs(f, preds_by_frame[fi], image_size[0] if image_size is not None else f.width,
                           _bop_depth_mm(f) if use_vsd else None, renderer, pairs if details else None)
        bop_targets += [_target_errors(inp, models[cls], cls, count) for cls, count in per_frame[fi]]
    out = _average_recalls(bop_targets, len(targets), use_vsd)
    out["notes"] = notes
    if details:
        out["details"] = {"pairs": pairs, "matches": _match_details(bop_targets, use_vsd)}
    return out


def _match_details(targets: list[BopTarget], use_vsd: bool) -> dict[str, list[dict[str, Any]]]:
    """Per error type, one record per (tau,) threshold and valid GT instance: the toolkit's
    ``matches_*.json`` content for the valid GT (scene_id, im_id, gt_id, est_id (-1: none))."""
    kinds = [("mssd", BOP19_MSSD_THRESHOLDS), ("mspd", BOP19_MSPD_THRESHOLDS)]
    if use_vsd:
        kinds.append(("vsd", BOP19_VSD_THRESHOLDS))
    out: dict[str, list[dict[str, Any]]] = {}
    for kind, ths in kinds:
        rows = out.setdefault(kind, [])
        for tg in targets:
            m = target_matches(tg, kind, ths)
            valid = _valid_gt(tg.visibility, tg.inst_count)
            for k in range(m.shape[0]):
                for j in range(m.shape[1]):
                    for g in np.flatnonzero(valid):
                        hit = np.flatnonzero(m[k, j] == g)
                        rows.append({"tau": k if kind == "vsd" else None, "threshold": j,
                                     "scene_id": tg.key[0], "im_id": tg.key[1],
                                     "gt_id": int(tg.gt_ids[g]),
                                     "est_id": int(tg.est_ids[hit[0]]) if len(hit) else -1})
    return out
