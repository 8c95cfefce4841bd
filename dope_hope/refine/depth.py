"""A depth image registered to the colour image: metres, its camera, checked once.

Every depth step (the line search, ICP) takes a :class:`DepthImage`. It is built once per
image at the boundary (:meth:`DepthImage.from_raw`: units, calibration, size and K checked,
converted to metres) and passed down; what makes a depth image unusable is recorded as
``problem`` (a one-line reason) rather than raised, so bad depth never changes a pose: the
refinement reports the reason and keeps the pose. Nonsense *settings* (a non-finite or
non-positive scale or calibration) are a user error and raise ConfigError.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dope_hope.errors import ConfigError

#: HOPE's RealSense depth scale correction. The HOPE dataset README says its depth images were
#: already multiplied by it before registration: use it only for raw RealSense captures.
HOPE_REALSENSE_DEPTH_CALIBRATION = 0.98042517
#: A depth image whose median valid depth lies beyond this (metres) is in other units than it is
#: read in (millimetres given as float metres, or a wrong depth scale): no RGB-D camera measures
#: a scene that far.
MAX_MEDIAN_DEPTH_M = 30.0
#: The median of that check is taken over every this-many-th row and column (a 720p frame's
#: full median costs ~10 ms, this one ~0.1 ms; the whole image where that sample holds no depth).
_UNIT_CHECK_STRIDE = 8


def _positive_finite(value: float, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True, eq=False)
class DepthImage:
    """Depth registered to the colour image.

    metres: (H, W) float64 metres, NaN where invalid (None when unusable).
    K: (3, 3) intrinsics of the colour image the depth is registered to.
    problem: "" when usable, else why not (one line).
    """

    metres: np.ndarray | None
    K: np.ndarray
    problem: str = ""

    @property
    def usable(self) -> bool:
        return not self.problem

    @property
    def hw(self) -> tuple[int, int] | None:
        return None if self.metres is None else (int(self.metres.shape[0]), int(self.metres.shape[1]))

    @classmethod
    def from_raw(cls, depth, K: np.ndarray, depth_scale_m: float = 0.001, calibration: float = 1.0,
                 image_hw: Sequence[int] | None = None) -> DepthImage:
        """Check and convert a raw depth image.

        Args:
            depth: (H, W) integer depth in units of ``depth_scale_m``, or float metres; 0 /
                NaN / inf = invalid. None gives an unusable DepthImage ("no depth image").
            K: (3, 3) intrinsics of the colour image (the depth is registered to it).
            depth_scale_m: metres per integer unit (0.001 = millimetres). calibration:
                multiplies the depth in metres (raw RealSense captures of the HOPE setup:
                :data:`HOPE_REALSENSE_DEPTH_CALIBRATION`).
            image_hw: (H, W) of the colour image, which the depth must match.
        """
        depth_scale_m = _positive_finite(depth_scale_m, "depth scale")
        calibration = _positive_finite(calibration, "depth calibration")
        K = np.asarray(K, dtype=np.float64)
        if depth is None:
            return cls(None, K, "no depth image")
        d = np.asarray(depth)
        if d.ndim == 3 and d.shape[2] == 1:
            d = d[..., 0]
        if d.ndim != 2 or d.size == 0:
            return cls(None, K, f"depth must be a 2-D image, got shape {d.shape}")
        H, W = d.shape
        if image_hw is not None and (H, W) != tuple(image_hw):
            return cls(None, K, f"depth is {W}x{H}, the image is {image_hw[1]}x{image_hw[0]}")
        # K's principal point sits near the image centre: a depth image of another resolution
        # (e.g. half size with a full-size K) puts it far off (2cx+1 vs W by > 25 %).
        implied_w, implied_h = 2 * K[0, 2] + 1, 2 * K[1, 2] + 1
        if not (0.75 < implied_w / W < 1.33 and 0.75 < implied_h / H < 1.33):
            return cls(None, K, f"depth is {W}x{H} but K implies about {implied_w:.0f}x{implied_h:.0f} "
                                "(principal point far from the depth image centre)")
        m = d.astype(np.float64) * (depth_scale_m if np.issubdtype(d.dtype, np.integer) else 1.0)
        m = m * calibration
        m[~np.isfinite(m) | (m <= 0)] = np.nan
        if not np.isfinite(m).any():
            return cls(None, K, "depth has no valid pixel (all zero / NaN)")
        sample = m[::_UNIT_CHECK_STRIDE, ::_UNIT_CHECK_STRIDE]  # the unit check needs no more (per frame)
        sample = sample[np.isfinite(sample)]
        median = float(np.median(sample if len(sample) else m[np.isfinite(m)]))
        if median > MAX_MEDIAN_DEPTH_M:
            read = ("float depth is read as metres" if not np.issubdtype(d.dtype, np.integer)
                    else f"integer depth is read in units of {depth_scale_m:g} m")
            return cls(None, K, f"depth's median is {median:.4g} m, beyond any depth camera's range "
                                f"({MAX_MEDIAN_DEPTH_M:g} m): wrong units? {read}")
        return cls(m, K)

    def problem_for(self, t: np.ndarray) -> str:
        """Why this depth cannot refine a pose with translation ``t`` (metres), or ""."""
        if self.problem:
            return self.problem
        if float(np.asarray(t).reshape(3)[2]) <= 0:
            return "pose is behind the camera (t_z <= 0)"
        return ""
