"""Cuboid keypoints, projection, rotations and the legacy keypoint frame.

Conventions (ARCHITECTURE.md): metres; OpenCV pinhole camera (x right, y down, z forward),
pixel centres at integer coordinates; a pose (R, t) maps model points into the camera frame,
``x_c = R @ x + t``. Rotations go through scipy's ``Rotation``; quaternions appear only at
file boundaries and always as ``quaternion_xyzw``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextvars import ContextVar

import numpy as np
from scipy.spatial.transform import Rotation

#: Half-extent signs (x, y, z) of cuboid corners 0..7, the order of the current official
#: DOPE data generators. Keypoint 8 is the box centre.
CUBOID_CORNER_SIGNS = np.array(
    [
        [+1, -1, +1],
        [-1, -1, +1],
        [-1, +1, +1],
        [+1, +1, +1],
        [+1, -1, -1],
        [-1, -1, -1],
        [-1, +1, -1],
        [+1, +1, -1],
    ],
    dtype=np.float64,
)
#: Metres per unit of a length in a file (meshes, BOP models, DOPE ``units``).
UNIT_SCALE: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: The flag that gives a file's length unit in the running command ("--units" in synth, train
#: and objects; "--mesh-units" in infer, evaluate, calibrate and import-official), which the
#: unit hints name (:func:`unit_hint`); None where the command has none (bop-submit: BOP's mm).
UNIT_FLAG: ContextVar[str | None] = ContextVar("unit_flag", default=None)


def unit_hint(unit: str) -> str:
    """``give its unit as cm (--units cm)``: the words of every "the file is likely in ..."
    message, with the running command's flag (:data:`UNIT_FLAG`) when it has one."""
    flag = UNIT_FLAG.get()
    return f"give its unit as {unit}" + (f" ({flag} {unit})" if flag else "")


def value_for_object(values: str | Mapping[str, str] | None, class_name: str) -> str | None:
    """The value a ``[NAME=]VALUE`` option gives ``class_name`` (``--mesh-units``, ``--up-axis``):
    ``values`` is one value for every object, or {class name: value} with "" for the others;
    None: none given (a mesh file's unit then goes by its suffix,
    :data:`dope_hope.io.meshes.DEFAULT_UNITS`)."""
    if isinstance(values, Mapping):
        return values.get(class_name, values.get(""))
    return values


NUM_KEYPOINTS = 9
CENTROID_INDEX = 8
#: Name recorded in checkpoints, datasets and ONNX metadata for the order above.
KEYPOINT_ORDER = "dope-current"
#: The order the official HOPE weights were trained in (a rotated object frame).
LEGACY_KEYPOINT_ORDER = "dope-legacy"

#: ``p_mesh = LEGACY_TO_MESH @ p_legacy``: the legacy keypoint frame of the official HOPE
#: weights is the mesh frame under this fixed rotation.
LEGACY_TO_MESH = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

#: Edges of the cuboid as pairs of corner indices (for drawing).
CUBOID_EDGES = (
    (0, 1), (1, 2), (2, 3), (3, 0),
    (4, 5), (5, 6), (6, 7), (7, 4),
    (0, 4), (1, 5), (2, 6), (3, 7),
)

#: Largest accepted deviation of a predicted R from a rotation matrix (Frobenius norm).
ROTATION_TOLERANCE = 1e-3


def cuboid_keypoints(size: np.ndarray, center: np.ndarray | None = None) -> np.ndarray:
    """Nine cuboid keypoints in the model frame.

    Args:
        size: (3,) full extents along x, y, z, metres.
        center: (3,) box centre in the model frame, metres (default: origin).

    Returns:
        (9, 3) float: corners 0..7 in the documented order, then the centre.
    """
    size = np.asarray(size, dtype=np.float64).reshape(3)
    center = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    corners = CUBOID_CORNER_SIGNS * (size / 2.0) + center
    return np.vstack([corners, center[None]])


def fit_cuboid(views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
               ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The one box whose nine keypoints, seen in each view's pose through its K, project to
    the views' keypoints: the size and centre that annotated projected cuboids imply (linear
    least squares: each keypoint's two projection equations are linear in size and centre).

    One view cannot tell a box from a larger one farther along the same ray; views from
    different directions can.

    Args:
        views: (keypoints (9, 2) pixels in the order of :data:`CUBOID_CORNER_SIGNS` (corners
            0..7, centre 8) in the frame of R, K (3, 3), R (3, 3), t (3,) metres) per instance.

    Returns:
        (size (3,) m, centre (3,) m in the object frame, RMS reprojection error in pixels over
        all views), or None when the views leave the box undetermined.
    """
    signs = np.vstack([CUBOID_CORNER_SIGNS, np.zeros((1, 3))])
    rows, rhs = [], []
    for keypoints, K, R, t in views:
        kp = np.asarray(keypoints, dtype=np.float64).reshape(NUM_KEYPOINTS, 2)
        K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
        for (u, v), sign in zip(kp, signs):
            # X = t + R c + R diag(sign / 2) s ; (K_i - p K_2) . X = 0 for (p, i) in ((u, 0), (v, 1))
            for p, i in ((u, 0), (v, 1)):
                a = K[i] - p * K[2]
                rows.append(np.concatenate([(a @ R) * sign / 2.0, a @ R]))
                rhs.append(-(a @ t))
    if not rows:
        return None
    A = np.asarray(rows)
    A_scaled = A / np.linalg.norm(A, axis=0).clip(1e-12)
    singular = np.linalg.svd(A_scaled, compute_uv=False)
    if singular[-1] < 1e-6 * singular[0]:
        return None
    x = np.linalg.lstsq(A, np.asarray(rhs), rcond=None)[0]
    size, center = x[:3], x[3:]
    if not np.all(size > 0):
        return None
    errors = [project_points(cuboid_keypoints(size, center), K, R, t) - np.asarray(kp, dtype=np.float64).reshape(-1, 2)
              for kp, K, R, t in views]
    return size, center, float(np.sqrt(np.mean(np.sum(np.concatenate(errors) ** 2, axis=1))))


def transform_points(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``R @ p + t`` for each row. points (N, 3), R (3, 3), t (3,) -> (N, 3)."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(R).T + np.asarray(t).reshape(1, 3)


def project_points(
    points: np.ndarray, K: np.ndarray, R: np.ndarray | None = None, t: np.ndarray | None = None
) -> np.ndarray:
    """Pinhole projection.

    Args:
        points: (N, 3) model points (or camera-frame points when R, t are None), metres.
        K: (3, 3) intrinsics.
        R, t: optional pose, (3, 3) and (3,) metres.

    Returns:
        (N, 2) pixel coordinates (u, v); points with z <= 0 give inf/nan.
    """
    pts = np.asarray(points, dtype=np.float64)
    if R is not None:
        pts = transform_points(pts, R, np.zeros(3) if t is None else t)
    uvw = pts @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[:, :2] / uvw[:, 2:3]


def project_points_poses(points: np.ndarray, K: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """:func:`project_points` of (N, 3) model points under B poses, Rs (B, 3, 3) and ts (B, 3)
    metres, at once: (B, N, 2) pixel coordinates (inf/nan where z <= 0)."""
    cam = np.asarray(points, dtype=np.float64) @ np.asarray(Rs, dtype=np.float64).transpose(0, 2, 1)
    uvw = (cam + np.asarray(ts, dtype=np.float64)[:, None]) @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[..., :2] / uvw[..., 2:3]


def inside_image(uv: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """(N,) bool: which (N, 2) pixel positions (u, v) lie on an (H, W) image, pixel centres at
    integers: [-0.5, W - 0.5] x [-0.5, H - 0.5], borders included; NaN is outside."""
    H, W = image_hw
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        return (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)


def projected_bbox(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   image_hw: tuple[int, int] | None) -> np.ndarray | None:
    """2D box [u_min, v_min, u_max, v_max] of model points projected under (R, t), pixels
    (pixel centres at integers), clipped to the image as the BOP toolkit's ``calc_2d_bbox``
    with ``clip=True`` ([0, W-1] x [0, H-1]); None when a point lies behind the camera or the
    box misses the image.

    points: (N, 3) model points, metres. K: (3, 3). R: (3, 3), t: (3,) metres.
    image_hw: (H, W) pixels, or None for no clipping.
    """
    return projected_bboxes(points, K, np.asarray(R)[None], np.asarray(t).reshape(1, 3), image_hw)[0]


def projected_bboxes(points: np.ndarray, K: np.ndarray, Rs: np.ndarray, ts: np.ndarray,
                     image_hw: tuple[int, int] | None) -> list[np.ndarray | None]:
    """:func:`projected_bbox` under B poses (Rs (B, 3, 3), ts (B, 3) metres) at once."""
    pts = np.asarray(points, dtype=np.float64)
    Rs, ts = np.asarray(Rs, dtype=np.float64), np.asarray(ts, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return [None] * len(Rs)
    cam = pts @ Rs.transpose(0, 2, 1) + ts[:, None]                        # (B, N, 3)
    behind = np.any(cam[..., 2] <= 0, axis=1)
    uvw = cam @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[..., :2] / uvw[..., 2:3]
    lo, hi = uv.min(axis=1), uv.max(axis=1)                                # (B, 2)
    if image_hw is not None:
        lo = np.maximum(lo, 0.0)
        hi = np.minimum(hi, [image_hw[1] - 1.0, image_hw[0] - 1.0])
    boxes = np.concatenate([lo, hi], axis=1)
    missing = behind | np.any(lo > hi, axis=1)
    return [None if m else b for m, b in zip(missing.tolist(), boxes)]


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) K from focal lengths and principal point, pixels."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


_PINHOLE_LAST_ROW = np.array([0.0, 0.0, 1.0])


def is_pinhole(K: np.ndarray) -> bool:
    """The pinhole rule for a (3, 3) finite K, the one check of every reader and the predictor:
    fx, fy > 0 and the last row ``0 0 1`` (within ``np.allclose``'s tolerances)."""
    return bool(K[0, 0] > 0 and K[1, 1] > 0
                and np.all(np.abs(K[2] - _PINHOLE_LAST_ROW) <= 1e-8 + 1e-5 * _PINHOLE_LAST_ROW))


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for the image resized by (sx, sy), under the pixel-centre-at-integer convention.

    A pixel edge at u = -0.5 stays at -0.5, so ``u' = sx * (u + 0.5) - 0.5``.
    """
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] *= sx
    K2[0, 1] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
    K2[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
    return K2


def quaternion_xyzw_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """(4,) scalar-last quaternion -> (3, 3) rotation (normalized first)."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=np.float64)).as_matrix()


def matrix_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) scalar-last quaternion with w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return q if q[3] >= 0 else -q


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees."""
    return float(np.degrees(Rotation.from_matrix(np.asarray(R_a).T @ np.asarray(R_b)).magnitude()))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to a (3, 3) matrix in Frobenius norm (drops scale and shear)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def checked_rotation(M: np.ndarray) -> np.ndarray:
    """The rule for a predicted R (JSON lines and BOP CSV alike): within
    ``ROTATION_TOLERANCE`` (Frobenius) of a rotation.

    Args:
        M: (3, 3) finite matrix.

    Returns:
        (3, 3) the nearest rotation.

    Raises:
        ValueError: M is no rotation (a reflection, a scaled or sheared matrix).
    """
    R = nearest_rotation(M)
    if np.linalg.norm(R - np.asarray(M, dtype=np.float64)) > ROTATION_TOLERANCE:
        raise ValueError("not a rotation matrix (rows must be orthonormal, det +1)")
    return R


def legacy_size_to_mesh(size_legacy: np.ndarray) -> np.ndarray:
    """Cuboid extents listed in the legacy frame (official DOPE configs) -> mesh frame. (3,)."""
    return np.abs(LEGACY_TO_MESH) @ np.asarray(size_legacy, dtype=np.float64)


def legacy_rotation_to_mesh(R_legacy: np.ndarray) -> np.ndarray:
    """A pose estimated in the legacy keypoint frame as a mesh-frame rotation: ``R L^T``."""
    return np.asarray(R_legacy, dtype=np.float64) @ LEGACY_TO_MESH.T


def mesh_rotation_to_legacy(R_mesh: np.ndarray) -> np.ndarray:
    """Inverse of :func:`legacy_rotation_to_mesh`: ``R_mesh L``."""
    return np.asarray(R_mesh, dtype=np.float64) @ LEGACY_TO_MESH


def _legacy_to_current_index() -> np.ndarray:
    # legacy corner k sits at mesh-frame signs L @ s_k, which is current corner j
    mapped = CUBOID_CORNER_SIGNS @ LEGACY_TO_MESH.T
    idx = [int(np.flatnonzero(np.all(CUBOID_CORNER_SIGNS == m, axis=1))[0]) for m in mapped]
    return np.array(idx + [CENTROID_INDEX])


#: ``current[LEGACY_TO_CURRENT_INDEX[k]] = legacy[k]``: legacy keypoint k is the same box
#: corner (in the mesh frame) as current keypoint ``LEGACY_TO_CURRENT_INDEX[k]``.
LEGACY_TO_CURRENT_INDEX = _legacy_to_current_index()


def legacy_keypoints_to_current(keypoints: np.ndarray) -> np.ndarray:
    """Reorder keypoints (..., 9, D) listed in the legacy order into the current order.

    Valid for a mesh-frame pose: the legacy keypoints of the box ``legacy_size`` are the
    current keypoints of ``legacy_size_to_mesh(legacy_size)`` in another order.
    """
    kp = np.asarray(keypoints)
    out = np.empty_like(kp)
    out[..., LEGACY_TO_CURRENT_INDEX, :] = kp
    return out
