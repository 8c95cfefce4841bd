"""Several working sizes of one image and their detections pooled: a trained model's
``multiscale`` settings, and the rule a new object's detector
(:class:`~dope_hope.inference.mesh_start.MeshStartPredictor`, its ``new_object.scales``) pools
its sizes by.

A network finds an object best at the sizes its training crops showed it; at one working
size an object far smaller or larger than those, or one the maps blur into its neighbour's
peaks, is lost, and another size finds it. Each of ``scales`` (multiples of the working size:
``height``, else the model's training scale) runs the network and the decoding; of the
detections of all sizes, highest score first, one whose 2D box overlaps an already kept one
of the same class by more than ``duplicate_iou`` is that object again, and dropped
(:func:`pool_detections`). Sizes 1, 0.75 and 1.33, on the 200 held-out frames of
``bench/e2e_accuracy.py`` (a 30-minute Ketchup model): 73 of the 294 bottles with no detection
at the run's threshold where size 1 alone loses 107, 72.4 % within 10 cm against 66.0 %; on
the six-object T = 10 model of ``bench/multi_object.py``: 96 of 291 instances lost against
146, 72 within 2 cm against 55 (bench/RESULTS.md). The cost: a network pass and a decoding
per size.

**The gate** (``multiscale.gate``): the other sizes run only where the first size's maps hold
what its detections do not explain: a belief above ``gate`` (any keypoint channel of an object)
outside the 2D boxes of that object's detections, widened by :data:`GATE_MARGIN_CELLS` map
cells (:func:`belief_beyond_boxes`). A frame whose objects the first size found, all of them,
then costs one size; a bottle it missed (a partly hidden one leaves weak peaks of its visible
corners) opens the gate. None (the default): every size runs on every frame.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dope_hope.config import SectionSettings, each, finite_float, fraction, or_none, positive_float
from dope_hope.inference.detection import Detection, box_iou

#: How far beyond a detection's 2D box its own belief blobs reach, map cells (the peaks of its
#: keypoints spread a few cells around the corners the box holds).
GATE_MARGIN_CELLS = 2


@dataclass(frozen=True)
class MultiscaleSettings(SectionSettings):
    """A trained model's working sizes (``multiscale:`` in ``dope_hope/configs/infer.yaml``;
    module docstring). scales: multiples of the working size, each run and their detections
    pooled (the default, one: the working size alone). duplicate_iou: two pooled detections of
    one class whose 2D boxes overlap more than this are one object (the higher-scoring kept);
    the new objects' sizes (``new_object.scales``) are pooled by it too. gate: the belief the
    first size's maps must reach outside its detections for the other sizes to run (module
    docstring; None: they always run)."""

    SECTION = "multiscale"
    RULES = {"scales": each(positive_float), "duplicate_iou": fraction, "gate": or_none(finite_float)}

    scales: tuple[float, ...] = (1.0,)
    duplicate_iou: float = 0.5
    gate: float | None = None


def belief_beyond_boxes(belief: np.ndarray, boxes: Sequence[np.ndarray], margin: int = GATE_MARGIN_CELLS) -> float:
    """The highest belief of one object's (C, h, w) maps outside its detections' ``boxes``
    (each (2, 2): [[u0, v0], [u1, v1]] in map cells) widened by ``margin`` cells; 0 where the
    boxes cover the maps."""
    outside = np.ones(belief.shape[1:], dtype=bool)
    h, w = outside.shape
    for (u0, v0), (u1, v1) in (np.asarray(b, dtype=np.float64) for b in boxes):
        if not np.all(np.isfinite([u0, v0, u1, v1])):
            continue
        r0, r1 = max(0, int(np.floor(v0)) - margin), min(h, int(np.ceil(v1)) + margin + 1)
        c0, c1 = max(0, int(np.floor(u0)) - margin), min(w, int(np.ceil(u1)) + margin + 1)
        outside[r0:r1, c0:c1] = False
    return float(belief[:, outside].max()) if outside.any() else 0.0


def scaled_height(base_height: int, scale: float) -> int:
    """The working height of ``scale`` times a working height of ``base_height`` px (at least 8)."""
    return max(8, round(base_height * scale))


def pool_detections(detections: Sequence[Detection], duplicate_iou: float) -> list[Detection]:
    """The detections of several working sizes as one list, highest score first: a detection
    whose ``bbox_2d`` overlaps a kept one of its class by an IoU above ``duplicate_iou`` is
    dropped."""
    kept: list[Detection] = []
    for det in sorted(detections, key=lambda d: -d.score):
        if all(k.class_name != det.class_name or box_iou(det.bbox_2d, k.bbox_2d) <= duplicate_iou for k in kept):
            kept.append(det)
    return kept
