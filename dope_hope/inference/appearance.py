"""Appearance check: does a detected cuboid hold this mesh's object, and which of its
symmetric-equivalent poses does the texture say?

A detector of a cuboid (the pretrained start, :mod:`dope_hope.inference.mesh_start`) finds
every object of that shape, and its pose only up to the cuboid's symmetries. For each
candidate pose, :class:`AppearanceCheck` renders the textured mesh unlit
(:class:`~dope_hope.render.textured.TexturedRenderer`) at each symmetric-equivalent pose
``R S`` into a small square crop around the object and compares it with the same crop of
the image inside the rendered silhouette:

- texture: normalized cross-correlation of the colour channels (each channel's mean
  removed; invariant to gain and offset, so to most of the lighting);
- colour: intersection of the normalized-chromaticity histograms (r, g = R, G over R + G + B;
  invariant to the brightness).

The score is their mean, in [0, 1] (a negative correlation counts as 0). The best
equivalent pose replaces the detection's; equivalent poses scoring within
``ambiguity_margin`` of it remain ambiguous, and a detection scoring under ``min_score`` is
a look-alike, dropped. CPU cost: one render of ``crop_px`` squared pixels per equivalent
pose (5-10 ms each at 64 px on 2 cores, Mesa llvmpipe).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dope_hope.config import SectionSettings, at_least, finite_float, nonnegative_float
from dope_hope.geometry import project_points


@dataclass(frozen=True)
class AppearanceSettings(SectionSettings):
    """crop_px: side of the compared crops, pixels. margin: the crop's border around the
    object's projected box, a fraction of its larger side. min_score: detections scoring
    lower are dropped (0 keeps all). ambiguity_margin: equivalent poses scoring within this
    of the best stay ambiguous. min_pixels: fewer silhouette pixels in the crop score 0.
    hist_bins: chromaticity histogram bins per axis."""

    SECTION = "appearance"
    RULES = {"crop_px": at_least(8), "margin": nonnegative_float, "min_score": finite_float,
             "ambiguity_margin": nonnegative_float, "min_pixels": at_least(1), "hist_bins": at_least(1)}

    crop_px: int = 64
    margin: float = 0.15
    min_score: float = 0.25
    ambiguity_margin: float = 0.03
    min_pixels: int = 30
    hist_bins: int = 8


@dataclass
class AppearanceResult:
    """One candidate's comparison: scores (S,) per equivalent pose (the check's rotations'
    order), best (index), R, t (the best equivalent pose), ambiguous (indices of the
    equivalent poses scoring within the margin of the best, the best excluded)."""

    scores: np.ndarray
    best: int
    R: np.ndarray
    t: np.ndarray
    ambiguous: tuple[int, ...]

    @property
    def score(self) -> float:
        return float(self.scores[self.best])


def crop_transform(box: np.ndarray, side_px: int, margin: float) -> tuple[np.ndarray, float]:
    """The square crop around a projected box [u_min, v_min, u_max, v_max] px: (2,) its
    top-left corner (u0, v0) and the scale s (crop px per image px); a crop pixel x shows the
    image at u0 + x / s."""
    lo, hi = np.asarray(box[:2], dtype=np.float64), np.asarray(box[2:], dtype=np.float64)
    side = max(float(np.max(hi - lo)) * (1.0 + 2.0 * margin), 4.0)
    centre = (lo + hi) / 2.0
    return centre - side / 2.0, side_px / side


def chromaticity_histogram(rgb: np.ndarray, bins: int) -> np.ndarray:
    """(bins, bins) normalized histogram of r = R / (R + G + B), g = G / (R + G + B) of (N, 3)
    colours (sums to 1; all zero for no pixel)."""
    c = np.asarray(rgb, dtype=np.float64)
    total = c.sum(axis=1) + 1e-6
    h, _, _ = np.histogram2d(c[:, 0] / total, c[:, 1] / total, bins=bins, range=((0, 1), (0, 1)))
    n = h.sum()
    return h / n if n > 0 else h


def appearance_similarity(image: np.ndarray, rendered: np.ndarray, mask: np.ndarray, bins: int) -> float:
    """Score in [0, 1] of (H, W, 3) ``image`` against (H, W, 3) ``rendered`` inside (H, W)
    ``mask``: the mean of the colour channels' normalized cross-correlation (negative: 0) and
    the chromaticity histograms' intersection."""
    a = np.asarray(image, dtype=np.float64)[mask]
    b = np.asarray(rendered, dtype=np.float64)[mask]
    a0, b0 = a - a.mean(axis=0), b - b.mean(axis=0)
    den = np.sqrt((a0 ** 2).sum() * (b0 ** 2).sum())
    ncc = float((a0 * b0).sum() / den) if den > 1e-9 else 0.0
    inter = float(np.minimum(chromaticity_histogram(a, bins), chromaticity_histogram(b, bins)).sum())
    return 0.5 * max(ncc, 0.0) + 0.5 * inter


class AppearanceCheck:
    """Render-and-compare of one mesh's candidate poses.

    Args:
        mesh: the textured ``trimesh.Trimesh``, metres, mesh frame.
        rotations: (S, 3, 3) mesh-frame rotations about ``center`` that leave the detector
            unable to tell the poses apart (identity first), e.g.
            :func:`dope_hope.symmetry.cuboid.cuboid_rotations`.
        center: (3,) the point they turn about (the cuboid centre), metres.
        settings: :class:`AppearanceSettings`.
    """

    def __init__(self, mesh, rotations: np.ndarray, center: np.ndarray,
                 settings: AppearanceSettings | None = None):
        from dope_hope.render.textured import TexturedRenderer

        self.settings = settings or AppearanceSettings()
        self.rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
        n = self.settings.crop_px
        self._renderer = TexturedRenderer(mesh, n, n)

    def equivalent_pose(self, R: np.ndarray, t: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose ``R S_k`` turned about the centre: the same cuboid, the ``k``-th equivalent."""
        Rk = np.asarray(R, dtype=np.float64) @ self.rotations[k]
        return Rk, np.asarray(t, dtype=np.float64) + R @ self.center - Rk @ self.center

    def compare(self, rgb: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> AppearanceResult:
        """Score every equivalent pose of the candidate (R (3, 3), t (3,) m) in the (H, W, 3)
        uint8 image with intrinsics K (3, 3)."""
        import cv2

        s = self.settings
        K = np.asarray(K, dtype=np.float64)
        scores = np.zeros(len(self.rotations))
        uv = project_points(self.hull, K, R, t)
        if float(np.asarray(t)[2]) <= 0 or not np.all(np.isfinite(uv)):
            return AppearanceResult(scores, 0, np.asarray(R, float), np.asarray(t, float), ())
        box = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
        (u0, v0), scale = crop_transform(box, s.crop_px, s.margin)
        M = np.array([[scale, 0.0, -u0 * scale], [0.0, scale, -v0 * scale]])
        crop = cv2.warpAffine(np.ascontiguousarray(rgb[..., :3]), M, (s.crop_px, s.crop_px), flags=cv2.INTER_AREA
                              if scale < 1 else cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inside = cv2.warpAffine(np.ones(rgb.shape[:2], np.uint8), M, (s.crop_px, s.crop_px),
                                flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
        K_crop = np.array([[scale, 0.0, -u0 * scale], [0.0, scale, -v0 * scale], [0.0, 0.0, 1.0]]) @ K
        poses = [self.equivalent_pose(R, t, k) for k in range(len(self.rotations))]
        for k, (Rk, tk) in enumerate(poses):
            rendered, mask = self._renderer.render(Rk, tk, K_crop)
            mask &= inside
            if mask.sum() >= s.min_pixels:
                scores[k] = appearance_similarity(crop, rendered, mask, s.hist_bins)
        best = int(np.argmax(scores))
        ambiguous = tuple(int(k) for k in np.flatnonzero(scores >= scores[best] - s.ambiguity_margin) if k != best)
        return AppearanceResult(scores, best, poses[best][0], poses[best][1], ambiguous)

    def close(self) -> None:
        """Free the renderer's GL context."""
        self._renderer.close()
