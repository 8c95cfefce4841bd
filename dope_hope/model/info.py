"""What inference needs to know about a model, validated once whatever file it came from.

A dope-hope checkpoint (``object``, ``keypoint_order``, ``normalization``, ``config.input``)
and a dope-hope ONNX file (``metadata_props``, :class:`dope_hope.inference.onnx_backend.
OnnxModelInfo`, a subclass) both become a :class:`ModelInfo`; :meth:`ModelInfo.validate` is
the one check of those fields (torch backend, ONNX backend and export all go through it).
No torch import here.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dope_hope.errors import ModelFileError
from dope_hope.geometry import KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER

#: Object frames a model may be trained in (see docs/ARCHITECTURE.md, "legacy frame").
OBJECT_FRAMES = ("mesh", "legacy")


@dataclass
class ModelInfo:
    """Model metadata.

    class_name: object the model detects. size_m: (3,) cuboid extents, mesh frame, metres.
    frame: "mesh" | "legacy". keypoint_order: "dope-current" | "dope-legacy" (must match frame).
    mean, std: the model's normalization of RGB in [0, 1]. input_hw: (H, W) training input
    size, or None when unknown. min_score: the model's own default pose-score threshold
    (chosen for it and recorded with its weights; None: the inference options' default);
    an explicit ``min_score`` still wins (:meth:`~dope_hope.inference.options.
    InferenceOptions.from_mapping`).
    """

    class_name: str
    size_m: tuple[float, float, float]
    frame: str
    keypoint_order: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    input_hw: tuple[int, int] | None
    min_score: float | None = field(default=None, kw_only=True)

    @property
    def legacy(self) -> bool:
        return self.frame == "legacy"

    def validate(self, path: str | os.PathLike) -> None:
        """Raise ModelFileError (one line, naming ``path``) for an inconsistent value."""
        def bad(problem: str):
            raise ModelFileError(path, f"model metadata: {problem}")

        for name in ("size_m", "mean", "std"):
            v = getattr(self, name)
            if v is None or len(v) != 3 or not np.all(np.isfinite(np.asarray(v, dtype=np.float64))):
                bad(f"{name} must hold 3 finite numbers, got {v}")
        if min(self.size_m) <= 0:
            bad(f"cuboid size {list(self.size_m)} is not positive")
        if min(self.std) <= 0:
            bad(f"std {list(self.std)} must be positive")
        expected = LEGACY_KEYPOINT_ORDER if self.frame == "legacy" else KEYPOINT_ORDER
        if self.frame not in OBJECT_FRAMES or self.keypoint_order != expected:
            bad(f"frame {self.frame!r} with keypoint order {self.keypoint_order!r} is not supported "
                f"(expected {expected!r})")
        if self.input_hw is not None and (len(self.input_hw) != 2 or min(self.input_hw) < 1):
            bad(f"input_hw must be [H, W] or null, got {self.input_hw}")
        if self.min_score is not None and (isinstance(self.min_score, bool) or not isinstance(
                self.min_score, (int, float)) or not math.isfinite(self.min_score) or self.min_score < 0):
            bad(f"min_score must be a finite number >= 0 or null, got {self.min_score!r}")

    @classmethod
    def from_checkpoint(cls, ckpt: dict[str, Any], path: str | os.PathLike = "<checkpoint>") -> ModelInfo:
        """The validated info of a checkpoint dict; ModelFileError for missing or bad fields."""
        obj = ckpt.get("object") or {}
        try:
            size = tuple(float(v) for v in np.asarray(obj.get("size_m"), dtype=np.float64).reshape(3))
        except (TypeError, ValueError):
            raise ModelFileError(path, "checkpoint 'object.size_m' must hold 3 extents in metres") from None
        norm = ckpt.get("normalization") or {}
        try:
            mean = tuple(float(v) for v in norm["mean"])
            std = tuple(float(v) for v in norm["std"])
        except (KeyError, TypeError, ValueError):
            raise ModelFileError(path, "checkpoint 'normalization' must hold mean and std") from None
        input_hw = None
        size_in = ((ckpt.get("config") or {}).get("input") or {}).get("size")
        if isinstance(size_in, (list, tuple)) and len(size_in) == 2:
            input_hw = (int(size_in[0]), int(size_in[1]))
        info = cls(class_name=str(obj.get("class_name")), size_m=size, frame=obj.get("frame", "mesh"),
                   keypoint_order=ckpt.get("keypoint_order", KEYPOINT_ORDER), mean=mean, std=std,
                   input_hw=input_hw, min_score=ckpt.get("min_score"))
        info.validate(path)
        return info
