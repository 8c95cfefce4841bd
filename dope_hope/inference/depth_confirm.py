"""Detections the depth confirms below the keypoints' threshold (``depth_confirm:``).

A bottle a third hidden, or one the briefly trained network sees faintly, leaves weak peaks:
its pose is found, often right, but its keypoint score falls under the object's threshold
(``min_score``) and the detection is dropped. Where ICP runs (depth, and a mesh or a catalog
box), the depth can vouch for such a pose instead: poses are searched down to
``depth_confirm.min_score``; one under the threshold is kept when ICP refined it
(``icp_applied``: it moved little, fits the depth no worse, and keeps its own depth support,
:mod:`dope_hope.refine.icp`) to a fit of at least ``min_fit`` (the soft share of the depth
points under it that lie on its surface). It is then flagged ``depth_confirmed``, keeps its
keypoint score in ``network_score``, and scores the object's threshold: it ranks after every
detection the keypoints keep alone. The others are dropped, as before.

On the held-out frames of ``bench/e2e_accuracy.py`` (the 1,790-step 30-minute Ketchup model,
the accurate preset, AVX2-only AMD EPYC; bench/RESULTS.md, "Inference presets"): of the poses
scoring 0.05 up to the model's threshold 0.45 that ICP brings to a fit of 0.95, 14 of 18 lie
within 2 cm of a bottle, a larger share than of those above the threshold (144 of 222); a fit
of 0.5 admits 112, 26 of them right. With the rule from 0.1: within 2 cm 48.6 -> 52.4 %, BOP's
targets with no detection 65 -> 53 of 258, a frame 1.47x (0.177 -> 0.261 s).
"""
from __future__ import annotations

from dataclasses import dataclass

from dope_hope.config import SectionSettings, fraction, or_none
from dope_hope.inference.detection import Detection


@dataclass(frozen=True)
class DepthConfirmSettings(SectionSettings):
    """``depth_confirm:`` in ``dope_hope/configs/infer.yaml`` (module docstring). min_score:
    the lowest pose score searched where ICP runs (None: off, the keypoints' threshold alone);
    min_fit: the ICP fit a pose under the threshold needs to be kept, in [0, 1]."""

    SECTION = "depth_confirm"
    RULES = {"min_score": or_none(fraction), "min_fit": fraction}

    min_score: float | None = None
    min_fit: float = 0.95


def pose_floor(min_score: float, settings: DepthConfirmSettings, icp_runs: bool) -> float:
    """The lowest pose score to search for an object of threshold ``min_score``: the
    confirmation's floor where ICP runs on it and the rule is on, else the threshold."""
    if settings.min_score is None or not icp_runs:
        return min_score
    return min(min_score, settings.min_score)


def worth_icp(det: Detection, min_score: float) -> bool:
    """Whether ICP should refine ``det`` (after -LS) for an object of threshold ``min_score``:
    always at or above it; under it only where -LS applied (the depth along the pose's ray agrees
    with it: most of the spurious poses a low floor lets in fail there, at a tenth of ICP's cost)."""
    return det.score >= min_score or det.ls_applied


def keep_detection(det: Detection, min_score: float, settings: DepthConfirmSettings) -> bool:
    """Whether ``det`` (after its depth stages) is kept by an object of threshold
    ``min_score``: at or above it as it is; under it when the depth confirms it (module
    docstring), then flagged and scored ``min_score`` in place."""
    if det.score >= min_score:
        return True
    if not (det.icp_applied and det.icp_fit >= settings.min_fit):
        return False
    det.network_score, det.score, det.depth_confirmed = det.score, float(min_score), True
    return True
