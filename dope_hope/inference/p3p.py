"""Many P3P problems at once: the pose of each of H minimal sets of three model points and
their image points, a fourth point choosing among the up-to-four solutions (:func:`ap3p_poses`).

The algorithm is Ke and Roumeliotis's algebraic P3P ("An Efficient Algebraic Solution to the
Perspective-Three-Point Problem", CVPR 2017) as OpenCV's AP3P writes it (the quartic's closed
form, two Newton steps on each root, the rotation and translation of each root), written here
over arrays of sets. It is hand-written because no library solves a batch of P3P problems:
OpenCV and kornia take one set per call, and the pose search of
:mod:`dope_hope.inference.pose_search` solves up to hundreds of sets per centroid, where one
``cv2.solvePnP`` call costs about 18 µs and the whole batch about 5 µs per set.

The fourth point chooses as ``cv2.solvePnP(..., flags=cv2.SOLVEPNP_AP3P)`` does: the solution
with the smallest summed squared reprojection error of the four points, in pixels. OpenCV 5.1's
AP3P returns fewer solutions than the quartic has real roots on some sets (of random cuboid
sets with 2 px of image noise, 9 % got a solution whose fourth point lies farther off than
another exact solution's, in front of the camera: tests/test_inference_p3p.py); here every real
root is kept, so a set's pose is OpenCV's or one that fits its four points better.
:func:`ap3p_each` is OpenCV's AP3P a call per set, with the same outputs, for a few sets.
"""
from __future__ import annotations

import cv2
import numpy as np

_NEXT, _AFTER = np.array([1, 2, 0]), np.array([2, 0, 1])   # the other two axes of each axis, cyclically


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3) cross products (the same floating-point operations as OpenCV's ``vect_cross``)."""
    return a[..., _NEXT] * b[..., _AFTER] - a[..., _AFTER] * b[..., _NEXT]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(...,) dot products of (..., 3) vectors."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _quartic_roots(a4, a3, a2, a1, a0) -> np.ndarray:
    """(H, 4) the real parts of the roots of a4 x^4 + a3 x^3 + a2 x^2 + a1 x + a0 (each (H,)),
    by Ferrari's closed form as OpenCV's AP3P computes it (a root of a complex pair gives its
    real part: the caller polishes every root and keeps those that solve the problem)."""
    a4_2, a3_2, a2a4 = a4 * a4, a3 * a3, a2 * a4
    a4_3 = a4_2 * a4
    p4 = (8 * a2a4 - 3 * a3_2) / (8 * a4_2)
    q4 = (a3_2 * a3 - 4 * a2a4 * a3 + 8 * a1 * a4_2) / (8 * a4_3)
    r4 = (256 * a0 * a4_3 - 3 * (a3_2 * a3_2) - 64 * a1 * a3 * a4_2 + 16 * a2a4 * a3_2) / (256 * (a4_3 * a4))
    p3 = ((p4 * p4) / 12 + r4) / 3
    q3 = (72 * r4 * p4 - 2 * p4 * p4 * p4 - 27 * q4 * q4) / 432
    root = np.sqrt((q3 * q3 - p3 * p3 * p3).astype(np.complex128))
    w = np.where(q3 >= 0, -root - q3, root - q3)
    w_real = np.cbrt(w.real)
    t = np.where(w.imag == 0.0, 2.0 * (w_real + p3 / w_real), 4.0 * (w ** (1.0 / 3)).real)
    sqrt_2m = np.sqrt((-2 * p4 / 3 + t).astype(np.complex128))
    shift = -a3 / (4 * a4)
    complex1 = 4 * p4 / 3 + t
    complex2 = 2 * q4 / sqrt_2m
    half = sqrt_2m.real / 2
    sqrt1 = np.sqrt(-(complex1 + complex2)).real / 2
    sqrt2 = np.sqrt(-(complex1 - complex2)).real / 2
    return np.stack([shift + half + sqrt1, shift + half - sqrt1, shift - half + sqrt2, shift - half - sqrt2], axis=1)


def ap3p_poses(objs: np.ndarray, imgs: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses of H minimal sets at once (no lens distortion).

    Args:
        objs: (H, 4, 3) model points, metres; the first three make the P3P problem, the
            fourth chooses among its solutions.
        imgs: (H, 4, 2) their image points, px.
        K: (3, 3) intrinsics.

    Returns:
        (R (h, 3, 3), t (h, 3), solved (H,) bool): ``x_cam = R x + t`` of the h sets that have
        a finite solution (degenerate sets, e.g. collinear points, have none), in input order.
    """
    objs = np.asarray(objs, dtype=np.float64).reshape(-1, 4, 3)
    imgs = np.asarray(imgs, dtype=np.float64).reshape(-1, 4, 2)
    K = np.asarray(K, dtype=np.float64)
    n_sets = len(objs)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    bearing = np.empty((n_sets, 3, 3))                          # unit rays of the three points
    bearing[..., 0] = (1.0 / fx) * imgs[:, :3, 0] - cx / fx
    bearing[..., 1] = (1.0 / fy) * imgs[:, :3, 1] - cy / fy
    bearing[..., 2] = 1.0
    bearing /= np.sqrt(_dot(bearing, bearing))[..., None]
    b1, b2, b3 = bearing[:, 0], bearing[:, 1], bearing[:, 2]
    w1, w2, w3 = objs[:, 0], objs[:, 1], objs[:, 2]
    with np.errstate(all="ignore"):  # degenerate sets give NaN / inf, dropped at the end
        u0 = w1 - w2
        nu0 = np.sqrt(_dot(u0, u0))
        k1 = u0 / nu0[:, None]
        u1 = w1 - w3
        k3, v1, v2, nl = _cross(np.stack([b1, b1, b2, u1]), np.stack([b2, b3, b3, k1]))
        nk3 = np.sqrt(_dot(k3, k3))
        k3 = k3 / nk3[:, None]
        tz = _cross(b1, k3)
        u1k1, k3b3 = _dot(u1, k1), _dot(k3, b3)
        delta = np.sqrt(_dot(nl, nl))
        nl = nl / delta[:, None]
        f11, f13, f15 = k3b3 * delta, _dot(k3, v1) * delta, -u1k1 * k3b3
        u2k1 = u1k1 - nu0
        f21_, f22_ = _dot(tz, v2), nk3 * k3b3
        f24, f25 = u2k1 * f22_, -u2k1 * f21_
        f21, f22, f23 = f21_ * delta, f22_ * delta, _dot(k3, v2) * delta
        g1, g2 = f13 * f22, f13 * f25 - f15 * f23
        g3, g4 = f11 * f23 - f13 * f21, -f13 * f24
        g5, g6, g7 = f11 * f22, f11 * f25 - f15 * f21, -f15 * f24
        coeffs = [g5 * g5 + g1 * g1 + g3 * g3, 2 * (g5 * g6 + g1 * g2 + g3 * g4),
                  g6 * g6 + 2 * g5 * g7 + g2 * g2 + g4 * g4 - g1 * g1 - g3 * g3,
                  2 * (g6 * g7 - g1 * g2 - g3 * g4), g7 * g7 - g2 * g2 - g4 * g4]
        cos1 = _quartic_roots(*coeffs)                                       # (H, 4) cos theta1'
        c4, c3, c2, c1, c0 = (c[:, None] for c in coeffs)
        for _ in range(2):
            value = (((c4 * cos1 + c3) * cos1 + c2) * cos1 + c1) * cos1 + c0
            slope = ((4 * c4 * cos1 + 3 * c3) * cos1 + 2 * c2) * cos1 + c1
            cos1 = cos1 - value / slope
        sin1 = np.sqrt(1 - cos1 * cos1) * np.where(k3b3 > 0, 1.0, -1.0)[:, None]
        g = [x[:, None] for x in (g1, g2, g3, g4, g5, g6, g7)]
        norm3 = sin1 / ((g[4] * cos1 + g[5]) * cos1 + g[6])
        cos3, sin3 = (g[0] * cos1 + g[1]) * norm3, (g[2] * cos1 + g[3]) * norm3
        c13 = np.empty((n_sets, 4, 3, 3))
        c13[..., 0, 0], c13[..., 0, 1], c13[..., 0, 2] = cos3, 0.0, -sin3
        c13[..., 1, 0], c13[..., 1, 1], c13[..., 1, 2] = sin1 * sin3, cos1, sin1 * cos3
        c13[..., 2, 0], c13[..., 2, 1], c13[..., 2, 2] = cos1 * sin3, -sin1, cos1 * cos3
        ck1nl = np.stack([k1, nl, _cross(k1, nl)], axis=2)                   # (H, 3, 3) columns
        cb1k3tz = np.stack([b1, k3, tz], axis=1)                             # (H, 3, 3) rows
        # OpenCV's R is the world in the camera's frame transposed: ours is its transpose.
        R = np.swapaxes(ck1nl[:, None] @ c13 @ cb1k3tz[:, None], 2, 3)      # (H, 4, 3, 3)
        t = (sin1[..., None] * ((delta / k3b3)[:, None] * b3)[:, None]
             - np.einsum("hsij,hj->hsi", R, w3))                              # (H, 4, 3)
        cam = np.einsum("hsij,hpj->hspi", R, objs) + t[:, :, None]           # (H, 4, 4, 3)
        px = cam[..., :2] / cam[..., 2:] * [fx, fy] + [cx, cy]
        err = ((px - imgs[:, None]) ** 2).sum(axis=(2, 3))                   # (H, 4) px^2
        err[~(np.abs(cos1) <= 1) | ~np.isfinite(err)] = np.inf
    best = np.argmin(err, axis=1)
    rows = np.arange(n_sets)
    R, t = R[rows, best], t[rows, best]
    solved = np.isfinite(err[rows, best]) & np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    return R[solved], t[solved], solved


def ap3p_each(objs: np.ndarray, imgs: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.SOLVEPNP_AP3P`` on each of (H, 4, 3) model / (H, 4, 2) image point quadruples (no
    distortion), one call per set, as :func:`ap3p_poses` returns them: ((h, 3, 3) R, (h, 3) t,
    (H,) solved): OpenCV's own AP3P, for a few sets, where :func:`ap3p_poses`' fixed cost
    (~0.25 ms) is that of ~14 calls."""
    Rs, ts, solved = [], [], np.zeros(len(objs), dtype=bool)
    for i, (obj, img) in enumerate(zip(objs, imgs)):
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, np.ascontiguousarray(img), K, None, flags=cv2.SOLVEPNP_AP3P)
        except cv2.error:
            continue
        if ok and np.isfinite(rvec).all() and np.isfinite(tvec).all():
            Rs.append(cv2.Rodrigues(rvec)[0])
            ts.append(tvec.ravel())
            solved[i] = True
    return np.array(Rs).reshape(-1, 3, 3), np.array(ts).reshape(-1, 3), solved
