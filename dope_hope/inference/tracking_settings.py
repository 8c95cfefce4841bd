"""The tracker's settings (``tracking:`` in ``dope_hope/configs/infer.yaml``), checked once.

Apart from :mod:`dope_hope.inference.tracking` so that the inference options can validate the
section without importing the tracker (which sits above the predictor).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from dope_hope.config import SectionSettings
from dope_hope.errors import ConfigError


@dataclass(frozen=True)
class TrackingSettings(SectionSettings):
    """The tracker's settings (``tracking:`` in ``dope_hope/configs/infer.yaml``).

    confirm_hits: detections that confirm a track. max_misses: frames without a detection
    that end a confirmed track. max_coast: frames a confirmed track is published without a
    detection (at most ``max_misses``). gate_m: largest distance between a track's predicted
    and a detection's translation for a match (metres; also the largest step between the
    measurements that restart a filter). min_iou: 2D box overlap with a confirmed track's
    prediction that keeps a new track's detection unpublished. rotation_weight: weight of the rotation difference (per 180 deg) in the
    matching cost. translation_std_m / rotation_std_deg: measurement noise of a detection.
    acceleration_m / angular_acceleration_deg: change of velocity per frame the motion model
    allows (std). rotation_gate_deg / rotation_reset / manoeuvre_gate / outlier_gate: see
    :class:`~dope_hope.inference.pose_filter.PoseFilter`. coast_refine: refine coasted poses
    against the depth; coast_search: the line search's scale range for them (and for
    reseeded detections). reseed_depth: match detections on a confirmed track's ray (module
    docstring). reprojection_px / reprojection_power: with reprojection_px > 0 a detection
    whose mean reprojection error e exceeds reprojection_px counts as
    ``(e / reprojection_px) ** reprojection_power`` times noisier (a partly hidden object's
    fit is worse; 0 = off).
    """

    SECTION = "tracking"

    confirm_hits: int = 3
    max_misses: int = 15
    max_coast: int = 5
    gate_m: float = 0.05
    min_iou: float = 0.3
    rotation_weight: float = 0.5
    translation_std_m: float = 0.002
    acceleration_m: float = 0.0001
    rotation_std_deg: float = 2.0
    angular_acceleration_deg: float = 0.02
    rotation_gate_deg: float = 45.0
    rotation_reset: int = 3
    manoeuvre_gate: float = 2.0
    outlier_gate: float = 6.0
    coast_refine: bool = True
    coast_search: tuple[float, float] = (0.95, 1.05)
    reseed_depth: bool = True
    reprojection_px: float = 0.0
    reprojection_power: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("coast_refine", "reseed_depth"):
                if not isinstance(v, bool):
                    raise ConfigError(f"tracking.{f.name} must be true or false, got {v!r}")
            elif f.name == "coast_search":
                ok = isinstance(v, (list, tuple)) and len(v) == 2 and all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
                if not ok or not 0 < v[0] <= 1 <= v[1]:
                    raise ConfigError(f"tracking.coast_search must be [lo, hi] with 0 < lo <= 1 <= hi, got {v!r}")
                object.__setattr__(self, f.name, (float(v[0]), float(v[1])))
            elif f.type == "int":
                if isinstance(v, bool) or not isinstance(v, int) or v < (0 if f.name == "max_coast" else 1):
                    raise ConfigError(f"tracking.{f.name} must be a whole number >= "
                                      f"{0 if f.name == 'max_coast' else 1}, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 \
                    or (v == 0 and f.name not in ("rotation_weight", "min_iou", "reprojection_px")):
                raise ConfigError(f"tracking.{f.name} must be a positive number, got {v!r}")
        if self.max_coast > self.max_misses:
            raise ConfigError(f"tracking.max_coast ({self.max_coast}) must not exceed tracking.max_misses "
                              f"({self.max_misses})")
        if self.min_iou > 1:
            raise ConfigError(f"tracking.min_iou must be in [0, 1], got {self.min_iou!r}")

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}
