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
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from dope_hope.config import SectionSettings, each, fraction, positive_float
from dope_hope.inference.detection import Detection, box_iou


@dataclass(frozen=True)
class MultiscaleSettings(SectionSettings):
    """A trained model's working sizes (``multiscale:`` in ``dope_hope/configs/infer.yaml``;
    module docstring). scales: multiples of the working size, each run and their detections
    pooled (the default, one: the working size alone). duplicate_iou: two pooled detections of
    one class whose 2D boxes overlap more than this are one object (the higher-scoring kept);
    the new objects' sizes (``new_object.scales``) are pooled by it too."""

    SECTION = "multiscale"
    RULES = {"scales": each(positive_float), "duplicate_iou": fraction}

    scales: tuple[float, ...] = (1.0,)
    duplicate_iou: float = 0.5


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
