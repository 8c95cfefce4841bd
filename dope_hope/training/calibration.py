"""Each object's own score threshold, chosen at the end of a run on its validation frames.

A network's pose scores are its own and, in a model of several objects, each object's are
too: at infer's default 0.5 a six-object model kept half the instances it places within 2 cm
(bench/RESULTS.md, "Multi-object"). So a run that ends (its steps, epochs or time budget;
not a stop) matches the estimates its chosen checkpoint makes at every score on the
validation frames, as `dope-hope calibrate` does on frames it is given
(:func:`dope_hope.evaluation.thresholds.calibrate_on_frames`: MeanSSD within 10 cm, the
threshold of highest F1 among 0.05 ... 0.95), and records each object's threshold in that
checkpoint (``objects[k].min_score``), which `infer`, `demo`, `export` and
:class:`~dope_hope.inference.predictor.DopePredictor` then use unless a ``min_score`` is given.
``train.calibrate_thresholds: false`` leaves it out; `dope-hope calibrate` chooses again on
other frames (real ones, say).

The objects' meshes are the run's (``--mesh`` / ``--models-dir``), else cuboids of the sizes
the run records; their symmetries as `evaluate` resolves them.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import DopeHopeError
from dope_hope.evaluation.object_models import load_models
from dope_hope.evaluation.thresholds import ThresholdChoice, calibrate_on_frames
from dope_hope.model.checkpoint import record_min_scores
from dope_hope.training.dataset import FrameRecord
from dope_hope.training.objects import RunObject
from dope_hope.training.settings import TrainJob
from dope_hope.training.sources import record_annotations

#: The trainer's logger: these lines are the trainer's, under its name.
log = logging.getLogger("dope_hope.training.trainer")
#: An object with fewer labelled instances among the validation frames keeps infer's default:
#: an F1 maximum over a handful of instances is noise (a user choosing on frames of their own
#: with `dope-hope calibrate` decides how many are enough).
MIN_INSTANCES = 20


def calibrate_run(weights: Path, job: TrainJob, val_records: Sequence[FrameRecord], objects: Sequence[RunObject],
                  progress: bool = False, device: str = "cpu", min_instances: int = MIN_INSTANCES) -> dict[str, Any]:
    """Choose each object's threshold for checkpoint ``weights`` (the run's chosen one) on the
    run's validation frames ``val_records`` (the network on ``device``; an object with fewer
    than ``min_instances`` instances there keeps its threshold) and record the choices in it
    (rewritten atomically, training state kept). Returns what the run's summary records:
    ``min_scores`` {class: threshold chosen}, ``min_scores_file`` (``weights``),
    ``min_score_frames`` and ``calibration_s``."""
    t0 = time.perf_counter()
    names = [o.name for o in objects]
    frames = record_annotations(val_records, job.val or job.data, names)
    meshes = [f"{n}={job.mesh_of(n)}" for n in names if job.mesh_of(n) is not None]
    units = {n: job.unit_of(n) for n in names if job.mesh_of(n) is not None and job.unit_of(n)}
    sizes = {o.name: (np.asarray(o.info["size_m"], dtype=np.float64), weights) for o in objects}
    models = load_models(names, meshes, None, units or None, recorded_sizes=sizes, mesh_required=(),
                         symmetry_args=[f"{names[0]}={job.symmetries}"] if job.symmetries and len(names) == 1 else [])
    choices, before = calibrate_on_frames(weights, frames, models, log=lambda line: log.info("thresholds: %s", line),
                                          progress=progress, device=device, min_instances=min_instances)
    if choices:
        record_min_scores(weights, {c: ch.min_score for c, ch in choices.items()})
        log.info("thresholds chosen on %d validation frames, recorded in %s: %s", len(frames), weights,
                 "; ".join(_described(c, before[n]) for n, c in choices.items()))
    return {"min_scores": {n: c.min_score for n, c in choices.items()}, "min_scores_file": str(weights),
            "min_score_frames": len(frames), "calibration_s": round(time.perf_counter() - t0, 2)}


class RunThresholds:
    """The end of a run: each object's threshold chosen on its validation frames.

    Args:
        enabled: ``train.calibrate_thresholds``.
        val_every: ``train.val_every`` (0: no validations, nothing to choose from).
        job: the run's job (its meshes, symmetries and folders).
        out: the run's output folder (its best.pt / last.pt).
        device: the network's device.
    """

    def __init__(self, enabled: bool, val_every: int, job: TrainJob, out: Path, device: str):
        self.enabled = enabled
        self.val_every = val_every
        self.job = job
        self.out = Path(out)
        self.device = device

    def calibrates(self, val_frames: int) -> bool:
        """Whether a run with ``val_frames`` validation frames ends by choosing each object's
        threshold on them (``train.calibrate_thresholds``, with validations on)."""
        return bool(self.enabled) and int(self.val_every) > 0 and val_frames > 0

    def choose(self, validated: bool, val_records: Sequence[FrameRecord], objects: Sequence[RunObject]
               ) -> dict[str, Any]:
        """Rank 0, at the end of a run that was not stopped, when it :meth:`calibrates`: each
        object's threshold chosen on ``val_records`` and recorded in the run's chosen
        checkpoint (best.pt; last.pt when no validation of this run made one, ``validated``
        False; :func:`calibrate_run`); what the summary records. A problem (a frame that
        cannot be read) is a warning: the trained weights stand."""
        if not self.calibrates(len(val_records)):
            return {}
        weights = self.out / ("best.pt" if validated and (self.out / "best.pt").is_file() else "last.pt")
        try:
            return calibrate_run(weights, self.job, val_records, objects, progress=self.job.progress,
                                 device=self.device)
        except DopeHopeError as exc:
            log.warning("thresholds not chosen (%s keeps infer's default): %s", weights.name, exc)
            return {}


def _described(choice: ThresholdChoice, before: ThresholdChoice) -> str:
    """``Can 0.35 (F1 0.675; 0.5: 0.555)``."""
    return f"{choice.class_name} {choice.min_score:g} (F1 {choice.f1:.3f}; {before.min_score:g}: {before.f1:.3f})"
