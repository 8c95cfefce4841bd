"""The demo's scoring and text: one scene's detections matched to its ground truth as
``dope-hope evaluate`` matches them (:func:`dope_hope.evaluation.matching.match_frame`, ADD-H
below 2 cm), the lines printed per scene and the summary."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dope_hope.evaluation.matching import DEFAULT_METRIC, METRIC_LABELS, TABLE_THRESHOLDS_M, match_frame, pose_errors

if TYPE_CHECKING:
    from dope_hope.evaluation.matching import PoseErrors


def keypoint_difference(a, b) -> float:
    """Largest distance (px) between the keypoints two backends found (finite in both);
    inf when one found a keypoint the other did not."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    fa, fb = np.isfinite(a).all(axis=1), np.isfinite(b).all(axis=1)
    if np.any(fa != fb):
        return math.inf
    if not fa.any():
        return 0.0
    return float(np.max(np.linalg.norm(a[fa] - b[fa], axis=1)))


def backend_agreement(dets_a: list, dets_b: list) -> float:
    """Max keypoint difference (px) between two backends' detections of one image, matched in
    score order; inf when they found different numbers of objects."""
    if len(dets_a) != len(dets_b):
        return math.inf
    return max([keypoint_difference(a.keypoints_2d, b.keypoints_2d) for a, b in zip(dets_a, dets_b)],
               default=0.0)


@dataclass
class SceneResult:
    """What the demo found in one scene (PyTorch backend). ``measurable``: the box is at least
    half visible (scenes that are not are left out of the count)."""

    name: str
    measurable: bool = True
    found: bool = False
    found_no_ls: bool = False
    found_icp: bool = False
    errors: PoseErrors | None = None
    errors_no_ls: PoseErrors | None = None
    errors_icp: PoseErrors | None = None
    onnx_diff_px: float | None = None
    extra_detections: int = 0
    n_gt: int = 0
    true_positives: int = 0
    lines: list[str] = field(default_factory=list)


def missing_weights_problem(mesh_path: Path) -> str:
    """What to do when the shipped demo model is absent (one line)."""
    return (f"demo model not found (this installation ships none); train one with the commands "
            f"in configs/demo.yaml (the demo mesh is written to {mesh_path}) and pass --weights "
            f"runs/demo/best.pt")


def _fmt_t(t) -> str:
    return "(" + ", ".join(f"{100 * v:6.1f}" for v in t) + ") cm"


def _err_text(e: PoseErrors) -> str:
    return (f"dt {e.te_cm:5.2f} cm  dR {e.re_deg:5.1f} deg  ADD-H {e.addh_cm:5.2f} cm  "
            f"MeanSSD {e.meanssd_cm:5.2f} cm")


def score_scene(res: SceneResult, gts: list, dets_plain: list, dets_ls: list, dets_icp: list, model) -> None:
    """Fill ``res`` (errors, found flags, printed lines) from one scene's detections without
    depth refinement, with -LS and with -LS + ICP, matched to the ground truth as ``dope-hope
    evaluate`` matches; a scene is found when every instance is."""
    plain, ls, icp = (match_frame(d, gts, model) for d in (dets_plain, dets_ls, dets_icp))
    res.found_no_ls, res.found, res.found_icp = plain.found, ls.found, icp.found
    res.n_gt, res.true_positives = len(gts), int(ls.correct.sum())
    for j, g in enumerate(gts):
        vis = "" if g.visibility is None else f", {100 * g.visibility:.0f} % visible"
        res.lines.append(f"    truth   t {_fmt_t(g.t)}{vis}")
        if ls.estimate_of_gt[j] < 0:
            res.lines.append("    not detected")
            continue
        if plain.estimate_of_gt[j] >= 0:
            d0 = dets_plain[plain.estimate_of_gt[j]]
            res.errors_no_ls = pose_errors(d0.R, d0.t, g, model)
            res.lines.append(f"    PnP     t {_fmt_t(d0.t)}  {_err_text(res.errors_no_ls)}  score {d0.score:.2f}")
        d = dets_ls[ls.estimate_of_gt[j]]
        res.errors = pose_errors(d.R, d.t, g, model)
        ls_note = f"scale {d.ls_scale:.4f}" if d.ls_applied else f"not applied: {d.ls_reason}"
        res.lines.append(f"    PnP+LS  t {_fmt_t(d.t)}  {_err_text(res.errors)}  "
                         + ("OK" if ls.correct[j] else "MISS") + f"  (-LS {ls_note})")
        if icp.estimate_of_gt[j] < 0:
            continue
        d2 = dets_icp[icp.estimate_of_gt[j]]
        res.errors_icp = pose_errors(d2.R, d2.t, g, model)
        icp_note = "applied" if d2.icp_applied else f"not applied: {d2.icp_reason}"
        res.lines.append(f"    +ICP    t {_fmt_t(d2.t)}  {_err_text(res.errors_icp)}  "
                         + ("OK" if icp.correct[j] else "MISS") + f"  (ICP {icp_note})")
    res.extra_detections = ls.unpaired
    if res.extra_detections:
        res.lines.append(f"    + {res.extra_detections} detection(s) without ground truth (false positives)")


def summary_lines(results: list[SceneResult], with_onnx: bool) -> list[str]:
    """The count ("found N/M scenes ...", M the measurable scenes), the medians over the
    detected measurable scenes, false positives and the backends' agreement."""
    counted = [r for r in results if r.measurable]
    n = len(counted)
    found, found0, found2 = (sum(getattr(r, k) for r in counted) for k in ("found", "found_no_ls", "found_icp"))
    criterion = f"{METRIC_LABELS[DEFAULT_METRIC]} < {100 * TABLE_THRESHOLDS_M[0]:g} cm"
    lines = [f"found {found}/{n} scenes with {criterion} (with -LS; without -LS: {found0}/{n}; "
             f"with -LS + ICP: {found2}/{n})"]
    if len(counted) < len(results):
        lines.append(f"  left out: {len(results) - n} scene(s) whose box stayed less than half visible")
    detected = [r for r in counted if r.errors is not None]
    if detected:
        med = np.median([r.errors.addh_cm for r in detected])
        plain = [r.errors_no_ls.addh_cm for r in detected if r.errors_no_ls is not None]
        med0 = f", {np.median(plain):.2f} cm without" if plain else ""
        medm = np.median([r.errors.meanssd_cm for r in detected])
        with_icp = [r.errors_icp.addh_cm for r in detected if r.errors_icp is not None]
        med2 = f", {np.median(with_icp):.2f} cm with -LS + ICP" if with_icp else ""
        lines.append(f"  median over {len(detected)} detected: ADD-H {med:.2f} cm with -LS{med0}{med2}; "
                     f"MeanSSD {medm:.2f} cm with -LS; "
                     f"{sum(r.extra_detections for r in counted)} false positive(s)")
    if with_onnx:
        diffs = [r.onnx_diff_px for r in results]
        same = sum(math.isfinite(d) for d in diffs)
        worst = max((d for d in diffs if math.isfinite(d)), default=0.0)
        lines.append(f"  ONNX vs PyTorch: same objects in {same}/{len(results)} scenes, "
                     f"keypoints within {worst:.3f} px")
    return lines


def next_steps(results: list[SceneResult], out: Path, mesh_path: Path) -> list[str]:
    """The `infer` and `evaluate` commands that read the demo's output, with the recall
    evaluate reports (the true positives with -LS over every scene's instances)."""
    tp, n_gt = sum(r.true_positives for r in results), sum(r.n_gt for r in results)
    recall = f"{tp / n_gt:.3f}" if n_gt else "n/a"
    return [f"  overlays: {out}/NNNNNN.overlay.png, {out / 'overview.png'}; frames: {out / 'frames'}",
            f"  next: dope-hope infer {out / 'frames' / '000000.png'} --depth auto --out {out / 'infer'}",
            f"  next: dope-hope evaluate -p {out / 'predictions.jsonl'} -d {out / 'frames'} --mesh "
            f"{mesh_path} --out {out / 'eval'}\n"
            f"        (reports recall {recall} at {100 * TABLE_THRESHOLDS_M[0]:g} cm "
            f"{METRIC_LABELS[DEFAULT_METRIC]}: the {tp} of {n_gt} instances found with -LS)"]
