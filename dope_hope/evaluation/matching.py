"""Per-pair pose errors and the one-to-one matching of predictions to ground truth.

Predictions are matched to GT one-to-one per image and class, greedily in descending score,
each taking the not-yet-matched GT instance of least error if that error is strictly below the
threshold (:func:`greedy_match`). :func:`pose_error` is the one place that turns a metric name
into an error value.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dope_hope.annotation import ObjectAnnotation
from dope_hope.errors import ConfigError
from dope_hope.evaluation import metrics
from dope_hope.evaluation.datasets import Dataset
from dope_hope.evaluation.models import ObjectModel
from dope_hope.io.predictions import Prediction

#: Table metrics (all in metres). "addh" is the HOPE paper's.
METRICS = ("addh", "add", "adds", "meanssd", "mssd")

#: Precision/recall thresholds of the per-object table, metres.
TABLE_THRESHOLDS_M = (0.02, 0.10)
#: Detection-rate curve thresholds, 0.5 .. 10 cm, metres.
CURVE_THRESHOLDS_M = tuple(round(0.005 * k, 4) for k in range(1, 21))


METRIC_LABELS = {"addh": "ADD-H", "add": "ADD", "adds": "ADD-S", "meanssd": "MeanSSD",
                 "mssd": "MSSD"}


DEFAULT_METRIC = "addh"


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


def compute_errors(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                   models: dict[str, ObjectModel], metric_names: Sequence[str],
                   upper: float | None = max(CURVE_THRESHOLDS_M),
                   progress: bool = False) -> list[GroupErrors]:
    """Error matrices for every (image, class) that has GT instances or predictions.

    ADD-H values above ``upper`` may be returned as a lower bound (>= ``upper``), which
    never changes a match at thresholds <= ``upper``.
    """
    from tqdm import tqdm

    groups = []
    for fi in tqdm(range(len(dataset.frames)), desc="errors", unit="img", disable=not progress):
        frame = dataset.frames[fi]
        classes = sorted({o.class_name for o in frame.objects} |
                         {p.class_name for p in preds_by_frame[fi]})
        for c in classes:
            gts = [o for o in frame.objects if o.class_name == c]
            ps = [p for p in preds_by_frame[fi] if p.class_name == c]
            errs = {}
            for m in metric_names:
                E = np.empty((len(ps), len(gts)))
                for i, p in enumerate(ps):
                    for j, g in enumerate(gts):
                        E[i, j] = pose_error(m, p.R, p.t, g, models[c], upper=upper)
                errs[m] = E
            groups.append(GroupErrors(fi, c, np.array([p.score for p in ps], dtype=np.float64),
                                      gts, errs))
    return groups
