"""Pose error metrics: ADD, ADD-S, ADD-H, MeanSSD, MSSD, MSPD, VSD, plus te/re.

Conventions: a pose is ``R`` (3, 3), ``t`` (3,) metres with ``x_c = R x + t``; model points
are (N, 3) metres in the model frame; symmetries are (S, 4, 4) model-frame rigid transforms
(metres) with the identity first (:mod:`dope_hope.symmetry.transforms`). All errors are in
metres, except MSPD (pixels), re (degrees) and VSD (a fraction in [0, 1]). The BOP errors (``mssd``, ``mspd``, ``vsd``) work in
whatever length unit they are given; BOP19 scoring gives them millimetres, as the toolkit.

Names and definitions follow the BOP toolkit (``bop_toolkit_lib/pose_error.py``):
``add``, ``adi`` (here :func:`adds`), ``mssd``, ``mspd``, ``vsd``, ``re``, ``te``; ``mssd``,
``mspd``, ``vsd`` and the point transforms also repeat its operations, so that exact ties at
thresholds decide as there. Two are
from the HOPE paper (Tyree et al., IROS 2022):

* **ADD-H** — mean distance between the model points in the two poses under the optimal
  one-to-one (Hungarian) assignment; symmetry-aware without a list of symmetries.
* **MeanSSD** — like MSSD but the mean instead of the max: the minimum over the symmetry
  transforms of the mean point distance.

ADD-H is computed exactly (see :func:`assignment_distance`); it is the optimum of the summed
Euclidean distances, not of squared distances.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

#: BOP19 VSD misalignment tolerances, fractions of the object diameter, exactly the toolkit's
#: ``np.arange(0.05, 0.51, 0.05)`` (0.05, 0.1, 0.15000000000000002, ...).
BOP19_VSD_TAUS = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
#: BOP19 VSD visibility tolerance, millimetres (15 for HOPE and most BOP datasets).
BOP19_VSD_DELTA_MM = 15.0


# Symmetry transforms are evaluated in chunks of this many points x symmetries, so that
# 720 symmetries x 500 points (cylinders in 1° steps) stay at a few MB.
_SYM_CHUNK_ELEMENTS = 64_000


# --------------------------------------------------------------------------- helpers
def _pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return R, t


def _points(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"model points must be (N, 3) with N > 0, got shape {pts.shape}")
    return pts


def transform_pts(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) model points -> (N, 3) camera-frame points ``R p + t``, with the BOP toolkit's
    operations (``misc.transform_pts_Rt``: ``(R.dot(pts.T) + t).T``)."""
    R, t = _pose(R, t)
    return (R.dot(_points(pts).T) + t.reshape((3, 1))).T


def project_pts(pts: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) model points -> (N, 2) pixel coordinates, with the BOP toolkit's operations
    (``misc.project_pts``: ``P = K [R | t]`` applied to homogeneous points)."""
    R, t = _pose(R, t)
    pts = _points(pts)
    P = np.asarray(K, dtype=np.float64).reshape(3, 3).dot(np.hstack((R, t.reshape((3, 1)))))
    pts_im = P.dot(np.hstack((pts, np.ones((pts.shape[0], 1)))).T)
    pts_im /= pts_im[2, :]
    return pts_im[:2, :].T


def _sym_list(syms: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(S, 4, 4) transforms -> [(R (3, 3), t (3, 1))], contiguous, as the toolkit holds them."""
    return [(np.ascontiguousarray(S[:3, :3]), np.ascontiguousarray(S[:3, 3]).reshape((3, 1)))
            for S in _symmetries(syms)]


def _symmetries(syms: np.ndarray | None) -> np.ndarray:
    if syms is None:
        return np.eye(4)[None]
    syms = np.asarray(syms, dtype=np.float64)
    if syms.ndim != 3 or syms.shape[1:] != (4, 4) or len(syms) == 0:
        raise ValueError(f"symmetries must be (S, 4, 4) with S > 0, got shape {syms.shape}")
    return syms


def te(t_e: np.ndarray, t_g: np.ndarray) -> float:
    """Translational error ``|t_e - t_g|``, metres."""
    return float(np.linalg.norm(np.asarray(t_e, float).reshape(3) - np.asarray(t_g, float).reshape(3)))


def re(R_e: np.ndarray, R_g: np.ndarray) -> float:
    """Rotational error (geodesic angle of ``R_e R_g^T``), degrees, in [0, 180]."""
    R_e = np.asarray(R_e, dtype=np.float64).reshape(3, 3)
    R_g = np.asarray(R_g, dtype=np.float64).reshape(3, 3)
    cos = 0.5 * (np.trace(R_e @ R_g.T) - 1.0)
    return float(np.degrees(math.acos(min(1.0, max(-1.0, cos)))))


# --------------------------------------------------------------------------- ADD family
def add(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
        pts: np.ndarray) -> float:
    """ADD: mean distance between corresponding model points in the two poses, metres."""
    e = transform_pts(pts, R_e, t_e)
    g = transform_pts(pts, R_g, t_g)
    return float(np.linalg.norm(e - g, axis=1).mean())


def adds(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
         pts: np.ndarray) -> float:
    """ADD-S (BOP ``adi``): mean distance from each GT point to the nearest estimated point."""
    e = transform_pts(pts, R_e, t_e)
    g = transform_pts(pts, R_g, t_g)
    d, _ = cKDTree(e).query(g, k=1)
    return float(np.mean(d))


def addh(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
         pts: np.ndarray, upper: float | None = None) -> float:
    """ADD-H: mean point distance under the optimal one-to-one assignment, metres.

    ``ADD-S <= ADD-H <= ADD`` always. The HOPE paper uses 500 model points.

    Args:
        upper: optional cut-off, metres. When a cheap lower bound already reaches it the
            exact value is not computed and that lower bound (>= ``upper``) is returned;
            useful when only errors below a threshold matter.
    """
    return assignment_distance(transform_pts(pts, R_g, t_g), transform_pts(pts, R_e, t_e),
                               upper=upper)


class _Buffers(threading.local):
    """Per-thread (n, n) float64 work matrices (``slot`` 0, 1, ...), reused across calls."""

    def __init__(self) -> None:
        self.cost: dict[tuple[int, int], np.ndarray] = {}

    def get(self, n: int, slot: int = 0) -> np.ndarray:
        buf = self.cost.get((n, slot))
        if buf is None:
            if len(self.cost) > 4:
                self.cost.clear()
            buf = self.cost[(n, slot)] = np.empty((n, n))
        return buf


_BUFFERS = _Buffers()


#: Below this size scipy's solver alone is already fast; the group warm start does not pay.
_WARM_START_MIN_N = 160


#: Number of interleaved sub-problems (each of ~n / 4 points) whose duals are averaged into
#: the group warm-start potential (measured optimum, bench/addh_speed.py: 2 or 3 groups leave
#: the final solve slower, 8 or 16 smaller ones too).
_WARM_START_GROUPS = 4


#: Bellman-Ford passes for each sub-problem's duals (about a third of what convergence takes;
#: the averaged warm start is as good, measured).
_WARM_START_BF_PASSES = 8


#: The group potentials are tried only when fewer than this fraction of the rows have
#: distinct minimisers under the linear potential (measured crossover, bench/addh_speed.py);
#: above it the linear potential alone leaves scipy's solver little to do.
_WARM_START_MAX_UNIQUE = 0.6


def _column_potentials(C: np.ndarray, match: np.ndarray, max_iter: int) -> np.ndarray:
    """Dual column potentials ``v`` of an optimal assignment ``i -> match[i]`` of ``C``.

    With ``u_i = C[i, match[i]] - v[match[i]]`` these satisfy ``u_i + v_j <= C_ij`` (up to
    rounding) and equality on the assignment: shortest-path distances in the residual
    graph, by a dense Bellman-Ford (hand-written: scipy's ``bellman_ford`` has no early
    exit and is an order of magnitude slower here). Of the many optimal duals this gives
    the largest ``v <= 0``; constants added to rows of ``C`` leave it unchanged. Stops
    early; the result only seeds a warm start, so an inexact one costs time, never
    correctness.
    """
    n = len(C)
    matched = C[np.arange(n), match]
    d = np.zeros(n)
    d_new = np.empty(n)
    work = np.empty_like(C)
    for _ in range(max_iter):
        row = d[match] - matched  # distance of row i: reached through its matched column
        np.add(C, row[:, None], out=work)
        np.minimum(d, work.min(axis=0), out=d_new)
        if (d - d_new).max() <= 1e-13:
            return d_new
        d, d_new = d_new, d
    return d


def _linear_potential(a: np.ndarray, b: np.ndarray, shift: np.ndarray, add: float) -> np.ndarray:
    """(n,) column potential ``v_j = k b_j . e``, ``e`` the unit centroid displacement ``shift``.

    With slope ``k = 1`` (and row potentials ``u_i = -a_i . e``) it is dual-feasible and
    reaches the centroid-distance bound; for a pure translation it is an optimal dual. When
    the motion is small against the object (identity cost ``add`` (mean) << the points' RMS
    radius) the optimal assignment is nearly the identity, whose displacements are only
    partly aligned with ``e``: the slope then falls towards their mean alignment
    ``|shift| / add``: ``k = (|shift| / add) ** max(0, 1 - add / rms)`` (a speed heuristic;
    results do not depend on it).
    """
    length = float(np.linalg.norm(shift))
    if length == 0 or add == 0:
        return np.zeros(len(b))
    rms = float(np.sqrt(((a - a.mean(axis=0)) ** 2).sum(axis=1).mean()))
    slope = min(1.0, length / add) ** max(0.0, 1.0 - add / rms) if rms > 0 else 1.0
    return b @ (shift * (slope / length))


def _group_potentials(C: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(n,) approximate column duals of ``C`` (n, n) from exact solves of interleaved sub-problems.

    The indices are split into ``_WARM_START_GROUPS`` interleaved groups ``g`` (every 4th
    point: for farthest-point samples each group is an even sample of the whole cloud) and
    each square sub-problem ``C[g, g]`` is solved exactly. Of its optimal duals roughly the
    largest ``v <= p`` is taken (a few Bellman-Ford passes on the sub-matrix minus ``p``:
    unconstrained columns keep its shape), and its row duals ``u`` are extended to all
    columns by the c-transform ``v_j = min_{i in g} (C_ij - u_i)`` (for a Euclidean cost the
    optimal duals are a 1-Lipschitz potential, so nearby points get nearby values). ``p`` is
    ``prior`` (n,) for the first group and the previous group's extension for the others
    (a closer start: shorter sub-problem solves). The result is the mean of the extensions,
    each shifted to mean 0: every sub-problem's duals carry their own discretisation error,
    and the mean is much closer to the full problem's duals than any one of them. Only a
    warm start: any ``v`` leaves the result exact.
    """
    n = len(C)
    total = np.zeros(n)
    p = prior
    block = _BUFFERS.get(n, 2)
    for offset in range(_WARM_START_GROUPS):
        g = slice(offset, None, _WARM_START_GROUPS)  # strided views: no copies of C's rows
        Cs = C[g, g] - p[g][None, :]  # a column constant: the sub-problem's solutions are unchanged
        low = Cs.min(axis=1)
        Cs -= low[:, None]  # row constants too; the duals below are taken back to C - p
        _, sub_match = linear_sum_assignment(Cs - Cs.min(axis=0))  # column minima: a faster solve
        v_sub = _column_potentials(Cs, sub_match, max_iter=_WARM_START_BF_PASSES)
        u_sub = Cs[np.arange(len(Cs)), sub_match] + low - v_sub[sub_match]
        rows = np.subtract(C[g], u_sub[:, None], out=block[:len(Cs)])
        p = rows.min(axis=0)
        total += p - p.mean()
    return total / _WARM_START_GROUPS


def _pair_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) ``|a_i - b_i|`` for (n, 3) ``a``, ``b``, with ``cdist``'s arithmetic (the square
    root of the squared differences summed in coordinate order): bitwise its diagonal."""
    d = a - b
    d *= d
    return np.sqrt(d.sum(axis=1))


def _distinct(idx: np.ndarray) -> int:
    """Number of distinct values in ``idx`` (n,) int, all in ``[0, n)``."""
    return int(np.count_nonzero(np.bincount(idx, minlength=len(idx))))


def _reduce(C: np.ndarray, v: np.ndarray, out: np.ndarray
            ) -> tuple[bool, np.ndarray, np.ndarray | None, float]:
    """Reduce ``C`` (n, n) by the column potential ``v`` (n,) and the row minima into ``out``.

    ``out = C - v`` minus each row's minimum; subtracting the returned column minima ``col``
    (n,) too (``out -= col``) makes it >= 0 with a zero in every row and column. Every
    permutation's total changes by the same constant, the dual bound ``D = sum(row minima)
    + sum(col) + sum(v)`` (a lower bound on every assignment's total cost).

    Returns:
        (whether the row-wise minimisers of ``C - v`` form a permutation — then it is an
        optimal assignment, ``out`` is left as ``C - v``, ``col`` is None and ``D`` is
        ``inf`` —, those (n,) minimisers, ``col``, ``D``).
    """
    np.subtract(C, v[None, :], out=out)
    arg = out.argmin(axis=1)
    if _distinct(arg) == len(arg):
        return True, arg, None, math.inf
    mins = out[np.arange(len(out)), arg]
    out -= mins[:, None]
    col = out.min(axis=0)
    return False, arg, col, float(mins.sum() + col.sum() + v.sum())


def assignment_distance(a: np.ndarray, b: np.ndarray, upper: float | None = None,
                        return_assignment: bool = False):
    """Mean Euclidean distance under the optimal one-to-one assignment of ``a`` to ``b``.

    ``min over permutations s of mean_i C[i, s(i)]``, ``C = cdist(a, b)``: the exact optimum
    of the summed (not squared) distances, the value ``linear_sum_assignment(C)`` gives.
    Found in this order:

    1. The identity (ADD when ``a``, ``b`` are the same model points in two poses) when it
       meets the centroid-distance lower bound ``|mean b - mean a|`` (a pure translation).
    2. A dual certificate: for a column potential ``v`` the row-wise minimisers of ``C_ij -
       v_j``, when they form a permutation, are an optimal assignment (every permutation's
       total differs from its reduced total by the same ``sum v``). ``v`` is the linear
       Kantorovich potential ``v_j = b_j . e``, ``e`` the unit centroid displacement
       (1-Lipschitz, so dual-feasible; optimal for translation-like motions; ``v = 0``,
       i.e. nearest neighbours, when the centroids coincide).
    3. Otherwise scipy's ``linear_sum_assignment`` on ``C`` reduced by ``v`` (see
       :func:`_reduce`): the optimal permutation is unchanged, but the closer ``v`` is to
       an optimal dual, the shorter the solver's augmenting paths. On hard problems (n >=
       160, < 60% distinct minimisers) the mean duals of exact solves of four interleaved
       quarter-size sub-problems (:func:`_group_potentials`) are tried too, and whichever
       potential gives the higher dual bound is used.

    Exactness: the reduced entries carry rounding errors of ~1e-16 of the largest
    distance, so a certified or reduced-matrix optimum is within that (per point) of the
    plain solver's; with a unique optimum the permutation and the value are bitwise
    scipy's, with ties (symmetric objects, duplicated points) another optimal permutation
    may be returned, of the same value to that rounding.

    Args:
        a, b: (n, 3) point sets, metres.
        upper: optional cut-off: if a lower bound (centroid distance, then the dual
            bound of step 3) is already >= ``upper``, that bound is returned instead of
            the exact value.
        return_assignment: also return ``s`` (n,) with ``a[i]`` assigned to ``b[s[i]]``
            (None when the ``upper`` cut-off was taken).

    Returns:
        The mean distance (float), or ``(distance, s)`` with ``return_assignment``.
    """
    a = _points(a)
    b = _points(b)
    if a.shape != b.shape:
        raise ValueError(f"point sets differ in size: {a.shape} vs {b.shape}")
    n = len(a)
    rows = np.arange(n)

    def result(perm: np.ndarray) -> float | tuple[float, np.ndarray]:
        value = float(C[rows, perm].mean())
        return (value, perm) if return_assignment else value

    def cut(bound: float) -> float | tuple[float, None]:
        return (bound, None) if return_assignment else bound

    shift = b.mean(axis=0) - a.mean(axis=0)
    centroid = float(np.linalg.norm(shift))
    ub = float(_pair_distances(a, b).mean())  # the identity's cost, = C[rows, rows].mean()
    if ub <= centroid + 1e-12 * max(ub, 1e-12):
        return (ub, rows) if return_assignment else ub
    if upper is not None and centroid >= upper:
        return cut(centroid)
    C = _BUFFERS.get(n, 0)
    cdist(a, b, out=C)

    perm, bound = _best_assignment(C, _linear_potential(a, b, shift, ub), upper)
    return cut(bound) if perm is None else result(perm)


def _best_assignment(C: np.ndarray, v: np.ndarray, upper: float | None) -> tuple[np.ndarray | None, float]:
    """Steps 2 and 3 of :func:`assignment_distance` on the (n, n) distances ``C`` from the
    (n,) column potential ``v``: (the optimal permutation (n,), NaN), or (None, the dual lower
    bound of the mean distance) when that bound already reaches ``upper``."""
    n = len(C)
    R = _BUFFERS.get(n, 1)
    optimal, arg, col, bound = _reduce(C, v, R)
    if optimal:
        return arg, float("nan")
    if n >= _WARM_START_MIN_N and _distinct(arg) < _WARM_START_MAX_UNIQUE * n:
        optimal, arg, col_sub, bound_sub = _reduce(C, _group_potentials(C, v), R)
        if optimal:
            return arg, float("nan")
        if bound_sub < bound:  # the linear potential was the better start after all
            _, _, col, _ = _reduce(C, v, R)
        else:
            col, bound = col_sub, bound_sub
    if upper is not None and bound >= upper * n:
        return None, bound / n
    R -= col[None, :]
    _, perm = linear_sum_assignment(R)
    return perm, float("nan")


# --------------------------------------------------------------------------- symmetry-aware
def _sym_chunks(syms: np.ndarray, n_points: int):
    per_chunk = max(1, _SYM_CHUNK_ELEMENTS // n_points)
    for start in range(0, len(syms), per_chunk):
        yield syms[start:start + per_chunk]


def _sym_model_points(pts: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(s, N, 3) model points under the symmetry transforms ``S`` (s, 4, 4)."""
    out = np.matmul(pts[None], S[:, :3, :3].transpose(0, 2, 1))
    out += S[:, None, :3, 3]
    return out


def mean_ssd(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
             pts: np.ndarray, syms: np.ndarray | None) -> float:
    """MeanSSD (HOPE paper): min over symmetries of the mean point distance, metres.

    Evaluated in the GT model frame, symmetries in chunks (distances are invariant to the GT
    pose: ``|R_g p' + t_g - e| = |p' - R_g^T (e - t_g)|``).
    """
    R_e, t_e = _pose(R_e, t_e)
    R_g, t_g = _pose(R_g, t_g)
    pts = _points(pts)
    syms = _symmetries(syms)
    q = (pts @ R_e.T + t_e - t_g) @ R_g  # estimated points in the GT model frame
    best = math.inf
    for S in _sym_chunks(syms, len(pts)):
        diff = _sym_model_points(pts, S)
        diff -= q[None]
        best = min(best, float(np.sqrt(np.einsum("sni,sni->sn", diff, diff)).mean(axis=1).min()))
    return best


def mssd(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
         pts: np.ndarray, syms: np.ndarray | None) -> float:
    """MSSD (BOP19): min over symmetries of the max point distance, in the unit of ``pts``
    and ``t``, with the BOP toolkit's operations (``pose_error.mssd``), so that its exact
    ties at thresholds decide as there."""
    R_e, t_e = _pose(R_e, t_e)
    R_g, t_g = _pose(R_g, t_g)
    pts = _points(pts)
    t_g = t_g.reshape((3, 1))
    pts_est = transform_pts(pts, R_e, t_e)
    es = []
    for R_s, t_s in _sym_list(syms):
        pts_gt_sym = transform_pts(pts, R_g.dot(R_s), R_g.dot(t_s) + t_g)
        es.append(np.linalg.norm(pts_est - pts_gt_sym, axis=1).max())
    return float(min(es))


def mspd(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, K: np.ndarray,
         pts: np.ndarray, syms: np.ndarray | None) -> float:
    """MSPD (BOP19): min over symmetries of the max 2D distance of projections, pixels, with
    the BOP toolkit's operations (``pose_error.mspd``)."""
    R_g, t_g = _pose(R_g, t_g)
    t_g = t_g.reshape((3, 1))
    proj_est = project_pts(pts, K, R_e, t_e)
    es = []
    for R_s, t_s in _sym_list(syms):
        proj_gt_sym = project_pts(pts, K, R_g.dot(R_s), R_g.dot(t_s) + t_g)
        es.append(np.linalg.norm(proj_est - proj_gt_sym, axis=1).max())
    return float(min(es))


def depth_to_distance(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) depth (z) -> (H, W) float64 distance from the camera centre, same unit, 0 stays 0.

    The BOP toolkit's ``misc.depth_im_to_dist_im_fast`` operations (pixel ``(x, y)`` at the
    integer coordinates of ``K``).
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    pre_x, pre_y = _pixel_rays(K, depth.shape)
    return np.sqrt(np.multiply(pre_x, depth) ** 2 + np.multiply(pre_y, depth) ** 2
                   + depth.astype(np.float64) ** 2)


_RAYS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _pixel_rays(K: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``((x - cx) / fx, (y - cy) / fy)`` over the pixel grid (cached per K and shape)."""
    key = (K.tobytes(), tuple(shape))
    rays = _RAYS.get(key)
    if rays is None:
        if len(_RAYS) > 8:
            _RAYS.clear()
        xs, ys = np.meshgrid(np.arange(shape[1]), np.arange(shape[0]))
        rays = _RAYS[key] = ((xs - K[0, 2]) / np.float64(K[0, 0]), (ys - K[1, 2]) / np.float64(K[1, 1]))
    return rays


def _visible(d_test: np.ndarray, d_model: np.ndarray, delta: float) -> np.ndarray:
    """The toolkit's "bop19" visibility: model surface not behind the test surface by more
    than ``delta``, or no test depth (difference taken in float32, as there)."""
    d_diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    return np.logical_and(np.logical_or(d_diff <= delta, d_test == 0), d_model > 0)


def vsd(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray,
        depth_test: np.ndarray, K: np.ndarray, model: tuple[np.ndarray, np.ndarray],
        delta: float, diameter: float, taus: Sequence[float] = BOP19_VSD_TAUS,
        cost_type: str = "step", renderer: Any = None) -> list[float]:
    """Visible Surface Discrepancy (Hodan et al.) with the BOP toolkit's operations
    (``pose_error.vsd``, visibility mode "bop19", normalized by the diameter).

    All lengths in one unit (BOP: millimetres): ``t_e``, ``t_g``, ``depth_test``, the model,
    ``delta`` and ``diameter``. The model is rendered in both poses
    (:class:`dope_hope.render.depth.DepthRenderer`, as the toolkit renders it), depths
    become distance images (:func:`depth_to_distance`), visibility masks are estimated against the
    test depth (pixels without test depth count as visible; the estimate's mask includes its
    pixels where the GT is visible).

    Args:
        depth_test: (H, W) test depth, 0 = no measurement (the toolkit: float32).
        K: (3, 3) intrinsics of the test image.
        model: (vertices (N, 3), faces (M, 3)) as in the model file.
        delta: visibility tolerance (BOP19: 15 mm).
        diameter: object diameter (the pixel distances are divided by it).
        taus: misalignment tolerances, fractions of the diameter (BOP19: 0.05 .. 0.5).
        cost_type: "step" (BOP19) or "tlinear" (the ECCVW'16 definition).
        renderer: an object with ``render_depth(model, R, t, K, width, height)`` (default: a
            shared :class:`~dope_hope.render.depth.DepthRenderer`).

    Returns:
        One VSD error in [0, 1] per tau.
    """
    if cost_type not in ("step", "tlinear"):
        raise ValueError(f"unknown VSD cost type {cost_type!r}; use 'step' or 'tlinear'")
    if depth_test.ndim != 2:
        raise ValueError(f"depth_test must be (H, W), got shape {depth_test.shape}")
    if renderer is None:
        from dope_hope.render.depth import default_renderer  # noqa: PLC0415 (OpenGL (pyrender's EGL) only for VSD)

        renderer = default_renderer()
    h, w = depth_test.shape
    depth_est = renderer.render_depth(model, R_e, t_e, K, w, h)
    depth_gt = renderer.render_depth(model, R_g, t_g, K, w, h)
    dist_test = depth_to_distance(depth_test, K)
    dist_gt = depth_to_distance(depth_gt, K)
    dist_est = depth_to_distance(depth_est, K)
    visib_gt = _visible(dist_test, dist_gt, delta)
    visib_est = np.logical_or(_visible(dist_test, dist_est, delta),
                              np.logical_and(visib_gt, dist_est > 0))
    visib_inter = np.logical_and(visib_gt, visib_est)
    visib_union_count = np.logical_or(visib_gt, visib_est).sum()
    visib_comp_count = visib_union_count - visib_inter.sum()
    dists = np.abs(dist_gt[visib_inter] - dist_est[visib_inter])
    dists /= diameter
    if visib_union_count == 0:
        return [1.0] * len(taus)
    errors = []
    for tau in taus:
        if cost_type == "step":
            costs = dists >= tau
        else:
            costs = dists / tau
            costs[costs > 1.0] = 1.0
        errors.append(float((np.sum(costs) + visib_comp_count) / float(visib_union_count)))
    return errors


def sphere_projections_overlap(radius: float, t_a: np.ndarray, t_b: np.ndarray) -> bool:
    """Whether the image projections of two spheres of ``radius`` at ``t_a``, ``t_b`` overlap.

    The BOP toolkit's approximate test (``misc.overlapping_sphere_projections``, same
    operations), used to skip rendering for VSD when the poses are far apart.
    """
    p1 = np.asarray(t_a, dtype=np.float64).reshape(3)
    p2 = np.asarray(t_b, dtype=np.float64).reshape(3)
    if p1[2] == 0 or p2[2] == 0:
        return False
    proj_dist = np.linalg.norm((p1 / p1[2])[:2] - (p2 / p2[2])[:2])
    return bool(proj_dist < radius * (1.0 / p1[2] + 1.0 / p2[2]))
