"""Per-pair pose errors and the one-to-one matching of estimates to ground truth.

Estimates are matched to GT one-to-one per image and class, greedily in descending score,
each taking the not-yet-matched GT instance of least error if that error is strictly below the
threshold (:func:`greedy_match`). :func:`pose_error` is the one place that turns a metric name
into an error value. ``dope-hope evaluate`` (:func:`compute_errors`) and ``dope-hope demo``
(:func:`match_frame`, :func:`pose_errors`) both count through here, so the demo's scenes
found equal evaluate's true positives on the same predictions.

**Which instances count** (``min_visible``, ``dope-hope evaluate --min-visible``): by default
every annotated instance, as HOPE's own evaluation counts them (NVlabs Deep_Object_Pose
``evaluate/evaluate.py`` and ``add_compute.py``, the scripts of the HOPE paper's DOPE figures:
every object of a frame's annotation is a GT instance, whatever its visibility); BOP19 counts
only instances at least a tenth visible (bop_toolkit's ``visib_gt_min`` 0.1). An instance under
the floor is matched like the others (an estimate of it is no false positive) but counts
neither as a GT instance nor, matched, as a detection: the toolkit's rule for GT instances that
are not valid. A missing visibility counts as visible.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from tqdm import tqdm

from dope_hope.annotation import ObjectAnnotation
from dope_hope.errors import ConfigError
from dope_hope.evaluation import metrics
from dope_hope.evaluation.datasets import VISIB_GT_MIN, Dataset
from dope_hope.evaluation.object_models import ObjectModel
from dope_hope.io.predictions import Prediction

#: Table metrics (all in metres). "addh" is the HOPE paper's.
METRICS = ("addh", "add", "adds", "meanssd", "mssd")

#: Precision/recall thresholds of the per-object table, metres.
TABLE_THRESHOLDS_M = (0.02, 0.10)
#: Detection-rate curve thresholds, 0.5 .. 10 cm, metres.
CURVE_THRESHOLDS_M = tuple(round(0.005 * k, 4) for k in range(1, 21))

#: Metric names -> labels in reports.
METRIC_LABELS = {"addh": "ADD-H", "add": "ADD", "adds": "ADD-S", "meanssd": "MeanSSD",
                 "mssd": "MSSD"}

#: The metric of the HOPE paper's tables (and of ``dope-hope demo``'s "found").
DEFAULT_METRIC = "addh"

#: Visible-fraction floors of the counted GT instances by convention (module docstring):
#: "hope" every annotated instance (the default), "bop19" those at least a tenth visible.
VISIBLE_FLOORS = {"hope": 0.0, "bop19": VISIB_GT_MIN}
#: The default floor: HOPE's own convention.
DEFAULT_MIN_VISIBLE = VISIBLE_FLOORS["hope"]


def visible_floor(value: float | str) -> float:
    """A visible-fraction floor: a name of :data:`VISIBLE_FLOORS` or a fraction in [0, 1];
    ConfigError naming ``--min-visible`` otherwise."""
    text = str(value).strip().lower()
    if text in VISIBLE_FLOORS:
        return VISIBLE_FLOORS[text]
    try:
        floor = float(text)
    except ValueError:
        floor = math.nan
    if not 0.0 <= floor <= 1.0:
        raise ConfigError(f"--min-visible: expected {', '.join(VISIBLE_FLOORS)} or a fraction in [0, 1], got {value!r}")
    return floor


#: :func:`counted_matches`' mark of an estimate matched to an instance under the floor.
UNCOUNTED = -2


class ScoredPose(Protocol):
    """What matching needs of an estimate (a :class:`~dope_hope.io.predictions.Prediction` or
    an inference ``Detection``): ``R`` (3, 3), ``t`` (3,) metres, ``score``."""

    R: np.ndarray
    t: np.ndarray
    score: float


# =========================================================================== errors + matching
def pose_error(metric: str, pred_R: np.ndarray, pred_t: np.ndarray, gt: ObjectAnnotation,
               model: ObjectModel, upper: float | None = None) -> float:
    """Error of one estimate against one GT instance, metres (``METRICS``)."""
    args = (pred_R, pred_t, gt.R, gt.t)
    if metric == "addh":
        return metrics.addh(*args, model.points, upper=upper)
    if metric == "add":
        return metrics.add(*args, model.points)
    if metric == "adds":
        return metrics.adds(*args, model.points)
    if metric == "meanssd":
        return metrics.mean_ssd(*args, model.points, model.symmetries)
    if metric == "mssd":
        return metrics.mssd(*args, model.points, model.symmetries)
    raise ConfigError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")


def error_matrix(metric: str, estimates: Sequence[ScoredPose], gts: Sequence[ObjectAnnotation],
                 model: ObjectModel, upper: float | None = None) -> np.ndarray:
    """(P, G) errors (metres) of every estimate against every GT instance of one class."""
    E = np.empty((len(estimates), len(gts)))
    for i, p in enumerate(estimates):
        for j, g in enumerate(gts):
            E[i, j] = pose_error(metric, p.R, p.t, g, model, upper=upper)
    return E


def greedy_match(errors: np.ndarray, scores: np.ndarray, threshold: float,
                 valid: np.ndarray | None = None) -> np.ndarray:
    """One-to-one greedy matching of estimates to GT instances (BOP ``match_poses``).

    Estimates are taken in descending score (ties: file order); each is matched to the valid,
    not yet matched GT instance of least error, if that error is strictly below
    ``threshold`` (ties: the first GT).

    Args:
        errors: (P, G) errors; scores: (P,); threshold: same unit as errors;
        valid: (G,) bool, GT instances that may be matched (default: all).

    Returns:
        (P,) int: the matched GT index, or -1.
    """
    errors = np.asarray(errors, dtype=np.float64)
    P, G = errors.shape
    match = np.full(P, -1, dtype=np.int64)
    if G == 0:
        return match
    taken = np.zeros(G, dtype=bool) if valid is None else ~np.asarray(valid, dtype=bool)
    for p in np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable"):
        e = np.where(taken | np.isnan(errors[p]), np.inf, errors[p])  # NaN never matches
        g = int(np.argmin(e))
        if e[g] < threshold:
            match[p] = g
            taken[g] = True
    return match


@dataclass
class GroupErrors:
    """Errors of the predictions of one class in one image against its GT instances."""

    frame: int
    class_name: str
    scores: np.ndarray                       # (P,)
    gt: list[ObjectAnnotation]               # G instances
    errors: dict[str, np.ndarray]            # metric -> (P, G) metres
    counted: np.ndarray | None = None        # (G,) bool: instances at or above the visible floor (None: all)

    @property
    def n_counted(self) -> int:
        """GT instances that count (at or above the visible floor)."""
        return len(self.gt) if self.counted is None else int(np.count_nonzero(self.counted))


def visible_enough(gts: Sequence[ObjectAnnotation], min_visible: float) -> np.ndarray:
    """(G,) bool: the instances whose visible fraction is at least ``min_visible`` (a missing
    visibility counts as 1)."""
    return np.array([(1.0 if g.visibility is None else float(g.visibility)) >= min_visible for g in gts], dtype=bool)


def counted_matches(group: GroupErrors, metric: str, threshold: float) -> np.ndarray:
    """(P,) the matches of :func:`greedy_match` over all of the group's GT instances at
    ``threshold`` (metres), with a match to an instance under the visible floor marked
    :data:`UNCOUNTED` (module docstring): >= 0 a true positive, -1 none."""
    match = greedy_match(group.errors[metric], group.scores, threshold)
    if group.counted is not None and len(group.gt):
        match[(match >= 0) & ~group.counted[np.maximum(match, 0)]] = UNCOUNTED
    return match


def compute_errors(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                   models: dict[str, ObjectModel], metric_names: Sequence[str],
                   upper: float | None = max(CURVE_THRESHOLDS_M),
                   progress: bool = False, min_visible: float = DEFAULT_MIN_VISIBLE) -> list[GroupErrors]:
    """Error matrices for every (image, class) that has GT instances or predictions.

    ADD-H values above ``upper`` may be returned as a lower bound (>= ``upper``), which
    never changes a match at thresholds <= ``upper``. ``min_visible``: the visible-fraction
    floor of the instances that count (module docstring; 0: all).
    """
    groups = []
    for fi in tqdm(range(len(dataset.frames)), desc="errors", unit="img", disable=not progress):
        frame = dataset.frames[fi]
        classes = sorted({o.class_name for o in frame.objects} |
                         {p.class_name for p in preds_by_frame[fi]})
        for c in classes:
            gts = [o for o in frame.objects if o.class_name == c]
            ps = [p for p in preds_by_frame[fi] if p.class_name == c]
            errs = {m: error_matrix(m, ps, gts, models[c], upper=upper) for m in metric_names}
            groups.append(GroupErrors(fi, c, np.array([p.score for p in ps], dtype=np.float64),
                                      gts, errs, visible_enough(gts, min_visible)))
    return groups


# =========================================================================== one frame (demo)
@dataclass
class FrameMatch:
    """How one frame's estimates of one class pair with its GT instances.

    Attributes:
        errors: (P, G) errors, metres.
        estimate_of_gt: (G,) index of the estimate paired with each GT instance, -1 for none:
            first the matches at the threshold (:func:`greedy_match`, what ``evaluate``
            counts), then the remaining estimates paired with the remaining GT the same way
            without a threshold (to show how far off they are).
        correct: (G,) bool, GT instances matched at the threshold (true positives).
    """

    errors: np.ndarray
    estimate_of_gt: np.ndarray
    correct: np.ndarray

    @property
    def found(self) -> bool:
        """Every GT instance (at least one) matched at the threshold."""
        return bool(len(self.correct)) and bool(self.correct.all())

    @property
    def unpaired(self) -> int:
        """Estimates paired with no GT instance (false positives)."""
        return len(self.errors) - int(np.count_nonzero(self.estimate_of_gt >= 0))


def match_frame(estimates: Sequence[ScoredPose], gts: Sequence[ObjectAnnotation], model: ObjectModel,
                metric: str = DEFAULT_METRIC, threshold: float = TABLE_THRESHOLDS_M[0]) -> FrameMatch:
    """Match one frame's estimates of one class to its GT instances as ``evaluate`` does.

    Args:
        estimates: P estimates (``R``, ``t`` metres, ``score``); gts: G GT instances;
        model: the class's model; metric: one of ``METRICS``; threshold: metres.
    """
    E = error_matrix(metric, estimates, gts, model)
    scores = np.array([float(p.score) for p in estimates], dtype=np.float64)
    at_threshold = greedy_match(E, scores, threshold)
    of_gt = np.full(len(gts), -1, dtype=np.int64)
    for p, g in enumerate(at_threshold):
        if g >= 0:
            of_gt[g] = p
    correct = of_gt >= 0
    rest = np.flatnonzero(at_threshold < 0)
    if len(rest):
        for k, g in enumerate(greedy_match(E[rest], scores[rest], math.inf, valid=~correct)):
            if g >= 0:
                of_gt[g] = rest[k]
    return FrameMatch(E, of_gt, correct)


@dataclass
class PoseErrors:
    """Errors of one pose against one GT instance: te (cm), symmetry-aware re (deg), ADD-H
    and MeanSSD (cm)."""

    te_cm: float
    re_deg: float
    addh_cm: float
    meanssd_cm: float


def pose_errors(R: np.ndarray, t: np.ndarray, gt: ObjectAnnotation, model: ObjectModel) -> PoseErrors:
    """te, re (the least over ``model.symmetries``), ADD-H and MeanSSD of one estimate
    (``R`` (3, 3), ``t`` (3,) metres) against ``gt``, by :func:`pose_error`."""
    rot = min(metrics.re(R, gt.R @ S[:3, :3]) for S in np.asarray(model.symmetries))
    return PoseErrors(te_cm=100.0 * metrics.te(t, gt.t), re_deg=rot,
                      addh_cm=100.0 * pose_error("addh", R, t, gt, model),
                      meanssd_cm=100.0 * pose_error("meanssd", R, t, gt, model))
