"""Each object's own score threshold, chosen on labelled frames: the score at which its
detections best balance the instances found against the false ones (the F1 score's maximum,
as detection toolkits report a detector's best confidence).

A network's scores are its own and, in a model of several objects, each object's are too: a
six-object model scores a lemon it places well lower than a can (bench/RESULTS.md,
"Multi-object"), so one ``min_score`` keeps the cans and drops the lemons.
:func:`match_estimates` takes estimates made with no threshold (``infer --min-score 0``)
on frames that were neither trained on nor benchmarked on, matches them to the labels as
``evaluate`` does (:func:`~dope_hope.evaluation.matching.greedy_match`: by descending score,
so a threshold never changes which of the estimates it keeps are true), and picks per object
the threshold of :data:`CANDIDATES` with the highest F1 (ties: the higher threshold, fewer
false detections). `dope-hope calibrate` records them with the weights
(:attr:`dope_hope.model.info.ObjectInfo.min_score`), and so does a training run at its end, on
its validation frames (:func:`calibrate_on_frames`, :mod:`dope_hope.training.calibration`).
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.evaluation.datasets import assign_predictions, load_dataset
from dope_hope.evaluation.evaluate import cuboid_centres_to_origins
from dope_hope.evaluation.matching import METRICS, error_matrix, greedy_match
from dope_hope.evaluation.object_models import ObjectModel, load_models
from dope_hope.inference.backends import backend_objects, model_min_score
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.images import read_depth_m, read_rgb
from dope_hope.io.models_dir import is_named_value
from dope_hope.io.predictions import Prediction, read_predictions
from dope_hope.model.checkpoint import load_checkpoint, save_inference_checkpoint
from dope_hope.model.info import ModelInfo, ObjectInfo

#: The thresholds a choice is made among: 0.05 to 0.95 in steps of 0.05.
CANDIDATES: tuple[float, ...] = tuple(round(0.05 * k, 2) for k in range(1, 20))


@dataclass(frozen=True)
class ThresholdChoice:
    """One object's chosen threshold and what it keeps on the calibration frames.

    min_score: the threshold. f1: ``2 true / (2 true + false + missed)`` there. true: its
    estimates within the distance of an instance (one per instance); false: the others;
    missed: instances without a true estimate; instances: all of them.
    """

    class_name: str
    min_score: float
    f1: float
    true: int
    false: int
    missed: int
    instances: int


def best_f1_threshold(class_name: str, scores: np.ndarray, true: np.ndarray, instances: int,
                      candidates: Sequence[float] = CANDIDATES) -> ThresholdChoice:
    """The candidate threshold of highest F1 for estimates of ``scores`` (n,) whose ``true``
    (n,) bool says which are matched to an instance, among ``instances`` labelled ones (ties:
    the higher threshold); ValueError without a candidate."""
    if not len(candidates):
        raise ValueError("no candidate threshold")
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    true = np.asarray(true, dtype=bool).reshape(-1)
    best: ThresholdChoice | None = None
    for t in sorted(candidates):
        kept = scores >= t
        tp, fp = int(np.count_nonzero(kept & true)), int(np.count_nonzero(kept & ~true))
        fn = instances - tp
        f1 = 2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else 0.0
        if best is None or f1 >= best.f1:
            best = ThresholdChoice(class_name, float(t), f1, tp, fp, fn, instances)
    assert best is not None
    return best


@dataclass(frozen=True)
class MatchedEstimates:
    """One object's estimates on labelled frames: scores (n,), true (n,) bool (matched to an
    instance within the distance), instances (labelled, all)."""

    scores: np.ndarray
    true: np.ndarray
    instances: int

    def at(self, class_name: str, candidates: Sequence[float] = CANDIDATES) -> ThresholdChoice:
        """:func:`best_f1_threshold` of these estimates."""
        return best_f1_threshold(class_name, self.scores, self.true, self.instances, candidates)


def log_unlabelled(current: Mapping[str, float], labelled: Collection[str], where: str,
                   log: Callable[[str], None]) -> None:
    """Say, for each object of ``current`` (name -> the threshold in use) without a labelled
    instance in ``where``, that its threshold stays (nothing can be chosen for it)."""
    for name in current:
        if name not in labelled:
            log(f"{name}: no labelled instance in {where}; its threshold stays {current[name]:g}")


def thresholds_in_use(objects: Sequence[ObjectInfo], model_min_score: float | None) -> dict[str, float]:
    """{class: the threshold `infer` runs each of ``objects`` at without --min-score}: the
    object's own, else the model's own ``model_min_score``, else configs/infer.yaml's (the
    resolution :class:`~dope_hope.inference.predictor.DopePredictor` makes)."""
    default = InferenceOptions.from_mapping(None, model_min_score=model_min_score).min_score
    return {o.class_name: default if o.min_score is None else float(o.min_score) for o in objects}


def match_estimates(frames: Sequence[FrameAnnotation], preds_by_frame: list[list[Prediction]],
                    models: dict[str, ObjectModel], classes: Sequence[str], metric: str = "meanssd",
                    within_m: float = 0.10, progress: bool = False) -> dict[str, MatchedEstimates]:
    """{class: its :class:`MatchedEstimates`} for each of ``classes``: an estimate is true when
    ``evaluate``'s matching pairs it with an instance of its class within ``within_m`` metres
    of ``metric`` (predictions per frame, as :func:`~dope_hope.evaluation.datasets.
    assign_predictions` gives them for a dataset's frames; ``models``: each class's model,
    symmetries included)."""
    scores: dict[str, list[float]] = {c: [] for c in classes}
    true: dict[str, list[bool]] = {c: [] for c in classes}
    instances = dict.fromkeys(classes, 0)
    for frame, preds in tqdm(list(zip(frames, preds_by_frame)), desc="matching", unit="img",
                             disable=not progress):
        for c in classes:
            gts = [o for o in frame.objects if o.class_name == c]
            estimates = [p for p in preds if p.class_name == c]
            instances[c] += len(gts)
            if not estimates:
                continue
            s = np.array([p.score for p in estimates], dtype=np.float64)
            matched = greedy_match(error_matrix(metric, estimates, gts, models[c], upper=within_m), s, within_m)
            scores[c] += s.tolist()
            true[c] += (matched >= 0).tolist()
    return {c: MatchedEstimates(np.array(scores[c]), np.array(true[c], dtype=bool), instances[c]) for c in classes}


def calibrate_weights(predictions: str | os.PathLike, dataset_dir: str | os.PathLike, weights: str | os.PathLike,
                      out: str | os.PathLike, *, fmt: str = "auto", metric: str = "meanssd", within_m: float = 0.10,
                      mesh: Sequence[str] = (), models_dir: str | os.PathLike | None = None,
                      mesh_units: str | Mapping[str, str] | None = None, symmetries: Sequence[str] = (),
                      progress: bool = False, log: Callable[[str], None] = print,
                      ) -> tuple[dict[str, ThresholdChoice], dict[str, ThresholdChoice]]:
    """Choose each object's threshold (:func:`match_estimates`, :func:`best_f1_threshold`) from
    the estimates in ``predictions`` (made by checkpoint ``weights`` with no threshold) on the
    labelled frames of ``dataset_dir``, and write ``weights`` with them to ``out``
    (:func:`~dope_hope.model.checkpoint.save_inference_checkpoint`). An object without a
    labelled instance, without an estimate or without a true one keeps its threshold;
    estimates of other objects (several models' in one file) are left out; both told through
    ``log``. Returns (the choices, what each object's
    threshold before kept) of the objects with labelled instances. ConfigError for a bad
    argument (an ONNX file, a metric, a distance, no estimate of the model's objects, frames
    without any of them, no object with both)."""
    for flag, path in (("--weights", weights), ("--out", out)):
        if Path(path).suffix.lower() != ".pt":
            raise ConfigError(f"{flag} {path}: give a checkpoint (.pt); export the calibrated checkpoint to ONNX")
    if Path(out).resolve() == Path(weights).resolve():
        raise ConfigError(f"--out {out} is --weights: write the calibrated weights beside them (the copy has no "
                          "training state to resume from)")
    if metric not in METRICS:
        raise ConfigError(f"--metric: unknown metric {metric!r}; use one of {', '.join(METRICS)}")
    if not (math.isfinite(within_m) and within_m > 0):
        raise ConfigError(f"--within-cm must be a positive distance, got {100 * within_m:g}")
    info = ModelInfo.from_checkpoint(load_checkpoint(weights), weights)
    current = thresholds_in_use(info.objects, info.min_score)
    dataset = load_dataset(dataset_dir, fmt)
    every, _ = read_predictions(predictions)
    preds = [p for p in every if p.class_name in current]
    if not preds:
        raise ConfigError(f"--predictions {predictions}: no estimate of {', '.join(current)} (the objects of "
                          f"{weights})")
    if len(preds) < len(every):  # several models' estimates in one file (infer --weights A --weights B)
        others = sorted({p.class_name for p in every} - set(current))
        log(f"{len(every) - len(preds)} estimates of {', '.join(others)} left out: not objects of {weights}")
    labelled = {o.class_name for f in dataset.frames for o in f.objects} & set(current)
    if not labelled:
        raise ConfigError(f"--dataset {dataset_dir}: no labelled instance of {', '.join(current)}")
    if min(p.score for p in preds) >= min(current.values()):
        log(f"warning: no estimate in {predictions} scores under {min(current.values()):g}: were they made "
            "with --min-score 0? (no lower threshold can be chosen)")
    by_frame, _ = assign_predictions(dataset, preds, predictions)
    classes = [c for c in current if c in labelled]
    # the labelled objects' models, and those of the model's other objects a NAME=... flag names
    named = {os.fspath(a).split("=", 1)[0] for a in [*mesh, *symmetries] if is_named_value(a)} | \
        (set(mesh_units) - {""} if isinstance(mesh_units, Mapping) else set())
    models = load_models([c for c in current if c in labelled or c in named], list(mesh), models_dir, mesh_units,
                         symmetry_args=list(symmetries), recorded_sizes=dataset.cuboid_sizes, mesh_required=classes)
    cuboid_centres_to_origins([p for p in preds if p.class_name in models], models)
    log_unlabelled(current, labelled, str(dataset_dir), log)
    matched = match_estimates(dataset.frames, by_frame, models, classes, metric, within_m, progress=progress)
    if not any(len(m.scores) for m in matched.values()):
        raise ConfigError(f"--predictions {predictions}: no estimate of an object labelled in {dataset_dir}")
    choices, before = choose_thresholds(matched, current, str(dataset_dir), within_m, log)
    save_inference_checkpoint(weights, out, object_min_scores={c: ch.min_score for c, ch in choices.items()})
    return choices, before


def estimates_on_frames(predictor: DopePredictor, frames: Sequence[FrameAnnotation],
                        progress: bool = False) -> list[list[Prediction]]:
    """Each frame's estimates by ``predictor`` (its own threshold and stages; the line search
    on the frame's depth image when it has one)."""
    out = []
    for frame in tqdm(frames, desc="estimates", unit="img", disable=not progress):
        if frame.image_path is None:
            raise InputFileError(frame.source, "no image beside the annotation")
        depth = None if frame.depth_path is None else read_depth_m(frame.depth_path, frame.depth_scale_m)
        dets = predictor.predict(read_rgb(frame.image_path), frame.K, depth=depth)
        out.append([Prediction(image=None, class_name=d.class_name, score=float(d.score), R=d.R, t=d.t,
                               ls_applied=d.ls_applied) for d in dets])
    return out


def calibrate_on_frames(weights: str | os.PathLike, frames: Sequence[FrameAnnotation],
                        models: Mapping[str, ObjectModel], within_m: float = 0.10, metric: str = "meanssd",
                        log: Callable[[str], None] = print, progress: bool = False, device: str = "cpu",
                        min_instances: int = 1,
                        ) -> tuple[dict[str, ThresholdChoice], dict[str, ThresholdChoice]]:
    """Choose each object's threshold for checkpoint ``weights`` on labelled ``frames`` (its
    estimates at every score, with the objects' meshes of ``models`` where they are not
    procedural stand-ins, matched with ``models``; the network on ``device``):
    :func:`choose_thresholds` of the objects labelled in them (``min_instances`` each); an
    object without a labelled instance keeps its threshold (said through ``log``). Records
    nothing."""
    predictor = DopePredictor(weights, backend="torch", device=device, min_score=0.0,
                              mesh={n: m.mesh for n, m in models.items() if not m.procedural} or None)
    current = thresholds_in_use(backend_objects(predictor.backend), model_min_score(predictor.backend))
    labelled = {o.class_name for f in frames for o in f.objects}
    log_unlabelled(current, labelled, "the frames", log)
    classes = [c for c in current if c in labelled]
    matched = match_estimates(frames, estimates_on_frames(predictor, frames, progress), dict(models), classes,
                              metric, within_m, progress=progress)
    return choose_thresholds(matched, current, "the frames", within_m, log, min_instances)


def choose_thresholds(matched: Mapping[str, MatchedEstimates], current: Mapping[str, float], where: str,
                      within_m: float, log: Callable[[str], None] = print, min_instances: int = 1,
                      ) -> tuple[dict[str, ThresholdChoice], dict[str, ThresholdChoice]]:
    """(each object's choice, what its ``current`` threshold keeps) for the objects of
    ``matched`` that can choose: one with fewer than ``min_instances`` labelled instances on
    the frames of ``where``, no estimate or no true one (no threshold keeps an instance)
    keeps its threshold, told through ``log``."""
    choices, before = {}, {}
    for name, m in matched.items():
        if m.instances < min_instances:
            log(f"{name}: {m.instances} labelled instance(s) on {where}, fewer than the {min_instances} a choice "
                f"needs; its threshold stays {current[name]:g}")
        elif not len(m.scores):
            log(f"{name}: no estimate on {where}; its threshold stays {current[name]:g}")
        elif not m.true.any():
            log(f"{name}: none of its {len(m.scores)} estimates is within {100 * within_m:g} cm of an "
                f"instance; its threshold stays {current[name]:g}")
        else:
            choices[name], before[name] = m.at(name), m.at(name, [current[name]])
    return choices, before


def thresholds_table(choices: dict[str, ThresholdChoice], before: dict[str, ThresholdChoice],
                     within_cm: float) -> str:
    """Markdown table of :func:`calibrate_weights`' choices: per object, the chosen threshold and
    what it keeps (true / false / missed, F1) beside the threshold before and what that kept."""
    rows = [f"| object | min score | true / false / missed (within {within_cm:g} cm) | F1 | before: min score, "
            "true / false / missed, F1 |", "|---|---|---|---|---|"]
    for name, c in choices.items():
        b = before[name]
        rows.append(f"| {name} | **{c.min_score:g}** | {c.true} / {c.false} / {c.missed} of {c.instances} | "
                    f"{c.f1:.3f} | {b.min_score:g}: {b.true} / {b.false} / {b.missed}, {b.f1:.3f} |")
    return "\n".join(rows)
