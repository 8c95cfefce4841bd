"""A new object's detector settings (``new_object:`` in ``dope_hope/configs/infer.yaml``), checked once.

Apart from :mod:`dope_hope.inference.mesh_start` so that the inference options can validate
the section without importing the predictor that reads it (which sits above the options).
"""
from __future__ import annotations

from dataclasses import dataclass

from dope_hope.config import SectionSettings, each, positive_float


@dataclass(frozen=True)
class NewObjectSettings(SectionSettings):
    """How the pretrained start runs as a detector of a new mesh's cuboid
    (:class:`~dope_hope.inference.mesh_start.MeshStartPredictor`; the check of its candidates
    is the ``appearance`` section).

    scales: the network's working sizes, multiples of the model's own (its training input
    size), each run and their detections pooled (the start saw objects of its training crops'
    sizes; two pooled detections are one object by ``multiscale.duplicate_iou``, the
    higher-scoring kept: :mod:`dope_hope.inference.scales`, whose ``multiscale.scales`` are a
    trained model's sizes)."""

    SECTION = "new_object"
    RULES = {"scales": each(positive_float)}

    scales: tuple[float, ...] = (1.0, 0.625)
