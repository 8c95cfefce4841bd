"""Depth line search ("-LS", the HOPE paper's refinement): rescale t along the viewing ray.

**Depth line search** (:func:`depth_line_search`, the HOPE paper's "-LS"). Monocular poses
are most uncertain along the viewing ray; with a depth image the translation is rescaled,
``t' = s t``, keeping R. The model points (a dense surface sampling, metres) are
projected under the initial pose and z-buffered on the image grid (the nearest point per
pixel, ``np.minimum.at``, then a minimum filter about as wide as the point spacing so that
the far side does not show through the gaps between front points); points within a small,
slope-aware margin of the nearest surface are *visible* (:func:`visible_points`; with
``model_normals`` back faces are culled first); visibility is decided once, under the
initial pose. For each candidate ``s`` the visible points are moved *exactly*,
``x_c = R x + s t`` - their depth is ``(R x)_z + s t_z``, not ``s`` times the old depth, and
they project to slightly different pixels, so the projection is recomputed for every
candidate (the "ray model", which scales the whole camera-frame object by ``s``, would keep
pixels fixed but change the object's size). The observed depth ``D`` is sampled bilinearly
(nearest pixel where a neighbour is invalid) and the cost is the median of ``|D - z|``
(``cost="median"``, robust to < 50 % occlusion) or the mean Huber loss (``cost="huber"``).
The search is bounded (``search``): a coarse grid, then ``scipy.optimize.minimize_scalar``
(bounded Brent) between the grid neighbours of the best node.

Bad depth never changes the pose: ``applied=False`` with a ``reason`` when the depth is
missing, not 2-D, of another size than the image (``image_hw``) or than ``K`` implies
(``2 c + 1`` more than 25 % away from the depth's width or height),
without valid pixels, when too few visible points have valid depth (``min_valid``), when the
optimum sits on the search bound or its residual exceeds ``max_residual_m``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from dope_hope.config import (
    SectionSettings,
    at_least,
    nonnegative_float,
    one_of,
    or_none,
    positive_float,
)
from dope_hope.errors import ConfigError
from dope_hope.refine.depth import DepthImage


def _scale_range(value: Any, name: str) -> tuple[float, float]:
    """The rule of a scale range ``[lo, hi]``: two finite numbers, 0 < lo <= hi."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(f"{name} must be [lo, hi], got {value!r}")
    lo, hi = positive_float(value[0], name), positive_float(value[1], name)
    if lo > hi:
        raise ConfigError(f"{name} must be [lo, hi] with lo <= hi, got {value!r}")
    return lo, hi


@dataclass(frozen=True)
class LineSearchSettings(SectionSettings):
    """The line search's settings (``line_search:`` in ``dope_hope/configs/infer.yaml``).

    search: (lo, hi) bounds of the scale s. min_valid: fewest visible points with valid
    depth. cost: "median" (median |D - z|) or "huber" (mean Huber loss, ``huber_delta_m``,
    metres). visibility_margin_m, splat_px: the visibility test (:func:`visible_points`;
    ``splat_px=None`` picks half the model points' spacing in pixels, :func:`auto_splat_px`).
    grid_steps: coarse grid size over ``search`` (at least 3). max_residual_m: refuse the
    result when the robust residual exceeds it, metres (None = off). wide_search: (lo, hi) of
    the second search a caller runs where the first one's optimum lay on its bound
    (:attr:`LineSearchResult.at_bound`; ``DopePredictor``'s -LS step); None: no second search.
    """

    SECTION = "line_search"
    RULES = {"search": _scale_range, "min_valid": at_least(1), "cost": one_of("median", "huber"),
             "huber_delta_m": positive_float, "visibility_margin_m": nonnegative_float,
             "splat_px": or_none(at_least(0)), "grid_steps": at_least(3), "max_residual_m": or_none(positive_float),
             "wide_search": or_none(_scale_range)}

    search: tuple[float, float] = (0.8, 1.25)
    min_valid: int = 50
    cost: str = "median"
    huber_delta_m: float = 0.01
    visibility_margin_m: float = 0.005
    splat_px: int | None = None
    grid_steps: int = 41
    max_residual_m: float | None = 0.02
    wide_search: tuple[float, float] | None = (0.5, 2.0)


@dataclass
class LineSearchResult:
    """Outcome of :func:`depth_line_search`.

    t: (3,) translation, metres (the input t when not applied).
    applied: whether t was changed. reason: "ok" or why not.
    scale: s with ``t = s * t_in`` (1.0 when not applied).
    residual_m: median |D - z| of the visible points at the optimum, metres (NaN when not
        evaluated).
    n_valid: visible model points with valid depth at the optimum.
    at_bound: whether the search refused its optimum for lying on the search bound (the
        depth agrees best beyond the range: a wider search may find the object).
    """

    t: np.ndarray
    applied: bool
    reason: str
    scale: float = 1.0
    residual_m: float = float("nan")
    n_valid: int = 0
    at_bound: bool = False


def visible_points(
    points_c: np.ndarray, K: np.ndarray, hw: tuple[int, int], splat_px: int = 2,
    margin_m: float = 0.005, max_slope: float = 2.0, normals_c: np.ndarray | None = None,
) -> np.ndarray:
    """Which camera-frame points are visible (front-most in their pixel neighbourhood).

    The nearest point per pixel is z-buffered (``np.minimum.at``), then the buffer is
    min-filtered over ``(2*splat_px+1)^2`` pixels so that the far side cannot show through
    the gaps between sampled front points. A point is visible if its depth is within
    ``margin_m + splat_px * (z / fx) * max_slope`` of that local minimum: the second term is
    the depth change of a surface inclined up to ``atan(max_slope)`` (63 deg) across the
    filter window, so inclined front faces are mostly not hidden by their own nearer parts
    (faces steeper than that can lose points: harmless, they only drop out of the fit).
    Given normals, back-facing points are dropped first, so none of the far side leaks in.

    Args:
        points_c: (N, 3) camera-frame points, metres.
        K: (3, 3). hw: (H, W) of the image.
        splat_px: filter radius, pixels; should be about the point spacing in pixels.
        margin_m: depth tolerance, metres. max_slope: see above.
        normals_c: optional (N, 3) camera-frame outward normals.

    Returns:
        (N,) bool; points behind the camera or outside the image are not visible.
    """
    H, W = hw
    z = points_c[:, 2]
    vis = np.zeros(len(points_c), dtype=bool)
    front = z > 1e-6
    if normals_c is not None:
        front &= np.einsum("ij,ij->i", np.asarray(normals_c, dtype=np.float64), points_c) < 0
    if not front.any():
        return vis
    uvw = points_c[front] @ K.T
    u = np.rint(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.rint(uvw[:, 1] / uvw[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    if not inside.any():
        return vis
    fi = np.flatnonzero(front)[inside]
    u, v, zf = u[inside], v[inside], z[fi]
    # Crop to the points' bounding box (plus the splat) to keep the filter cheap.
    u0, v0 = max(u.min() - splat_px, 0), max(v.min() - splat_px, 0)
    u1, v1 = min(u.max() + splat_px, W - 1), min(v.max() + splat_px, H - 1)
    hh, ww = v1 - v0 + 1, u1 - u0 + 1
    pix = (v - v0) * ww + (u - u0)
    zbuf = np.full(hh * ww, np.inf)
    np.minimum.at(zbuf, pix, zf)  # nearest point per pixel
    zbuf = zbuf.reshape(hh, ww)
    if splat_px > 0:
        zbuf = minimum_filter(zbuf, size=2 * splat_px + 1, mode="nearest")
    tol = margin_m + splat_px * zf / K[0, 0] * max_slope
    vis[fi] = zf <= zbuf.ravel()[pix] + tol
    return vis


def auto_splat_px(model_points: np.ndarray, K: np.ndarray, depth_m: float) -> int:
    """Half the typical spacing of the model points in pixels at ``depth_m``, in [1, 6].

    The spacing is the median nearest-neighbour distance (scipy cKDTree, on at most 1000
    query points); a (2r+1)-wide window then covers the gaps between front points.
    """
    P = np.ascontiguousarray(model_points, dtype=np.float64)
    if len(P) < 2:
        return 1
    spacing_px = _point_spacing_m(P.reshape(-1, 3).tobytes()) * float(K[0, 0]) / max(depth_m, 1e-6)
    return int(np.clip(np.ceil(spacing_px / 2.0), 1, 6))


@functools.lru_cache(maxsize=64)
def _point_spacing_m(points: bytes) -> float:
    """The median nearest-neighbour distance of the float64 (N, 3) points in ``points`` (N >=
    2), metres, of at most 1000 of them; kept per point set (one tree per model, not per
    detection)."""
    P = np.frombuffer(points).reshape(-1, 3)
    d, _ = cKDTree(P).query(P[:: max(1, len(P) // 1000)], k=2)
    return float(np.median(d[:, 1]))


def sample_depth(D: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear depth at (u, v); nearest pixel where a neighbour is invalid; NaN outside."""
    H, W = D.shape
    out = np.full(u.shape, np.nan)
    ok = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    if not ok.any():
        return out
    uu, vv = u[ok], v[ok]
    x0 = np.clip(np.floor(uu).astype(np.int64), 0, W - 2 if W > 1 else 0)
    y0 = np.clip(np.floor(vv).astype(np.int64), 0, H - 2 if H > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = uu - x0, vv - y0
    d00, d01, d10, d11 = D[y0, x0], D[y0, x1], D[y1, x0], D[y1, x1]
    bil = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    near = D[np.rint(vv).astype(np.int64), np.rint(uu).astype(np.int64)]
    out[ok] = np.where(np.isfinite(bil), bil, near)
    return out


@dataclass
class _ScaleCost:
    """The disagreement with the depth image of the visible model points at scale ``s`` of the
    translation: ``X = A + s t`` (A (M, 3) rotated model points, camera frame, metres)."""

    A: np.ndarray
    t: np.ndarray
    K: np.ndarray
    D: np.ndarray
    min_valid: int
    cost: str
    huber_delta_m: float

    def depth_minus_z(self, scales: np.ndarray) -> np.ndarray:
        """(S, M) depth minus point depth, metres, of every point at each of ``scales`` (S,);
        NaN where the depth has none or the point leaves the image."""
        X = self.A[None] + np.asarray(scales, dtype=np.float64)[:, None, None] * self.t  # (S, M, 3)
        uvw = X @ self.K.T
        z = uvw[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return sample_depth(self.D, uvw[..., 0] / z, uvw[..., 1] / z) - z

    def residuals(self, s: float) -> np.ndarray:
        """(M',) depth minus point depth, metres, where both are finite."""
        r = self.depth_minus_z(np.array([s]))[0]
        return r[np.isfinite(r)]

    def __call__(self, s: float) -> float:
        """The robust cost (median |r| or mean Huber); inf with too few valid points."""
        return float(self.costs(np.array([s]))[0])

    def costs(self, scales: np.ndarray) -> np.ndarray:
        """(S,) the cost of :meth:`__call__` at each of ``scales`` (S,), all in one array pass
        (the line search's grid)."""
        a = np.abs(self.depth_minus_z(scales))  # NaN: no depth
        n = np.isfinite(a).sum(axis=1)
        out = np.full(len(a), np.inf)
        rows = n >= max(self.min_valid, 1)
        a, n = a[rows], n[rows]
        if self.cost == "median":  # NaNs sort last: each row's median of its n finite values
            a = np.sort(a, axis=1)
            lo = np.take_along_axis(a, ((n - 1) // 2)[:, None], axis=1)[:, 0]
            hi = np.take_along_axis(a, (n // 2)[:, None], axis=1)[:, 0]
            out[rows] = 0.5 * (lo + hi)
            return out
        d = self.huber_delta_m
        loss = np.where(a <= d, 0.5 * a * a, d * (a - 0.5 * d))
        out[rows] = np.nansum(loss, axis=1) / n
        return out


def _best_scale(objective: _ScaleCost, search: tuple[float, float],
                grid_steps: int) -> tuple[float, bool] | None:
    """The scale minimizing ``objective``: a grid over ``search``, then a bounded search around
    the grid's best. Returns (scale, whether it sits at a search bound), or None when no
    scale has valid depth."""
    lo, hi = float(search[0]), float(search[1])
    grid = np.linspace(lo, hi, grid_steps)
    costs = objective.costs(grid)
    if not np.isfinite(costs).any():
        return None
    i = int(np.argmin(costs))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    # Scales without enough valid depth cost inf; the bounded search then subtracts inf from
    # inf (NaN steps) and numpy warns. Its answer is kept only when it beats the grid's best.
    with np.errstate(invalid="ignore", over="ignore"):
        res = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": 1e-6})
    s_best = float(res.x) if np.isfinite(res.fun) and res.fun <= costs[i] else grid[i]
    step = grid[1] - grid[0]
    at_lo = i == 0 and s_best <= lo + 0.5 * step
    at_hi = i == len(grid) - 1 and s_best >= hi - 0.5 * step
    return s_best, bool(at_lo or at_hi)


def depth_line_search(
    R: np.ndarray,
    t: np.ndarray,
    model_points: np.ndarray,
    depth: DepthImage,
    settings: LineSearchSettings = LineSearchSettings(),
    model_normals: np.ndarray | None = None,
) -> LineSearchResult:
    """Rescale the translation along its ray to agree with a depth image (HOPE "-LS").

    Args:
        R: (3, 3), t: (3,) metres: the pose to refine (``x_c = R x + t``).
        model_points: (N, 3) model surface points, metres (a few thousand is plenty).
        depth: the depth image in metres with its K (:class:`~dope_hope.refine.depth.DepthImage`).
        settings: :class:`LineSearchSettings` (search range, cost, visibility, refusals).
        model_normals: optional (N, 3) outward normals of the model points (back-face culling).

    Returns:
        :class:`LineSearchResult`; ``t`` unchanged with a reason when not applied.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    K = depth.K

    def refuse(reason: str, **kw) -> LineSearchResult:
        return LineSearchResult(t=t.copy(), applied=False, reason=reason, **kw)

    problem = depth.problem_for(t)
    D = depth.metres
    if problem:
        return refuse(problem)

    P = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    A = P @ R.T  # camera-frame points without translation
    splat_px = auto_splat_px(P, K, float(t[2])) if settings.splat_px is None else settings.splat_px
    normals_c = None if model_normals is None else np.asarray(model_normals, float).reshape(-1, 3) @ R.T
    vis = visible_points(A + t, K, D.shape, splat_px, settings.visibility_margin_m, normals_c=normals_c)
    if not vis.any():
        return refuse("object does not project into the depth image")
    A = A[vis]

    f = _ScaleCost(A, t, K, D, settings.min_valid, settings.cost, settings.huber_delta_m)
    n0 = f.residuals(1.0).size
    if n0 < settings.min_valid:
        return refuse(f"too few visible points with valid depth ({n0} < {settings.min_valid})", n_valid=n0)
    found = _best_scale(f, settings.search, settings.grid_steps)
    if found is None:
        return refuse("no valid depth along the search range", n_valid=n0)
    s_best, at_bound = found
    n_valid = int(f.residuals(s_best).size)
    residual = float(np.median(np.abs(f.residuals(s_best))))
    if at_bound:
        return refuse(f"optimum at the search bound (s = {s_best:.3f})",
                      residual_m=residual, n_valid=n_valid, at_bound=True)
    max_residual_m = settings.max_residual_m
    if max_residual_m is not None and residual > max_residual_m:
        return refuse(f"depth residual {residual * 1000:.1f} mm > {max_residual_m * 1000:.1f} mm",
                      residual_m=residual, n_valid=n_valid)
    return LineSearchResult(t=s_best * t, applied=True, reason="ok", scale=s_best,
                            residual_m=residual, n_valid=n_valid)
