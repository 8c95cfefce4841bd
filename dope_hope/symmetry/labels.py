"""Symmetry-aware keypoint labels: one canonical corner order per view of a symmetric object.

A symmetric object looks the same under a symmetry ``S`` of its category (a bottle turned
180° about its vertical axis), but the cuboid corners of the poses ``R`` and ``R S`` are
numbered differently: the network is asked to tell apart corners that the image cannot
tell apart, and learns to hedge between them (weak, split peaks; mixed-up corners). The
standard cure (Pitteri et al., "On Object Symmetries and 6D Pose Estimation from Images",
3DV 2019) relabels each training instance with the symmetric pose for which the camera
lies nearest to a fixed reference direction of the object, so the same view always gets the
same labels. The pose the network then yields is one of the symmetric equivalents of the
true pose, which the symmetry-aware metrics (MeanSSD, MSSD, MSPD, ADD-S, ADD-H) score as
exact.

Only symmetries that map the cuboid's corners onto corners are used (rotations by 180°
about the box axes; 90° about the vertical axis too when the box's cross-section is
square); with them relabelling is a permutation of the nine projected keypoints.
"""
from __future__ import annotations

import numpy as np

from dope_hope.geometry import NUM_KEYPOINTS, cuboid_keypoints

#: The object-frame direction the camera is brought nearest to (a generic direction, so
#: that no symmetry group's decision boundary runs through a common view).
REFERENCE_VIEW = np.array([0.2, 0.5, 1.0]) / np.linalg.norm([0.2, 0.5, 1.0])


def corner_permutations(size_m: np.ndarray, symmetries: np.ndarray,
                        tol: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The symmetries that map the cuboid's keypoints onto each other.

    Args:
        size_m: (3,) cuboid extents, metres (mesh frame, box centred on the origin).
        symmetries: (S, 4, 4) or (S, 3, 3) model-frame symmetry transforms (identity included),
            e.g. :func:`dope_hope.symmetry.transforms.category_symmetries`.
        tol: largest corner mismatch accepted, as a fraction of the box diagonal.

    Returns:
        (rotations (P, 3, 3), permutations (P, 9) int) with ``S @ c[k] == c[perm[k]]``; the
        identity is always among them.
    """
    cub = cuboid_keypoints(np.asarray(size_m, dtype=np.float64))
    limit = tol * float(np.linalg.norm(size_m))
    rots, perms = [], []
    for S in np.asarray(symmetries, dtype=np.float64):
        Sc = cub @ S[:3, :3].T
        dist = np.linalg.norm(Sc[:, None] - cub[None], axis=2)
        perm = dist.argmin(axis=1)
        if dist[np.arange(NUM_KEYPOINTS), perm].max() <= limit and len(set(perm.tolist())) == NUM_KEYPOINTS:
            if not any(np.array_equal(perm, p) for p in perms):
                rots.append(S[:3, :3])
                perms.append(perm)
    if not perms:
        rots, perms = [np.eye(3)], [np.arange(NUM_KEYPOINTS)]
    return np.stack(rots), np.stack(perms)


def camera_direction(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3,) unit direction from the object's origin to the camera, in the object frame.

    Args:
        R: (3, 3) object -> camera rotation; t: (3,) translation, metres.
    Returns NaNs when ``t`` is zero or not finite.
    """
    v = -np.asarray(R, dtype=np.float64).T @ np.asarray(t, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if np.isfinite(n) and n > 0 else np.full(3, np.nan)


def canonical_index(view_dir: np.ndarray, rotations: np.ndarray,
                    reference: np.ndarray = REFERENCE_VIEW) -> int | None:
    """Index of the symmetry ``S`` (among (P, 3, 3) ``rotations``) whose pose ``R S`` puts the
    camera nearest to ``reference``; None for a NaN ``view_dir``.

    With pose ``R S`` the camera direction in the object frame is ``S^T v``.
    """
    v = np.asarray(view_dir, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        return None
    score = np.einsum("pij,i,j->p", rotations, v, reference)  # (S^T v) . ref = v . (S ref)
    return int(np.argmax(score))


def canonical_permutation(view_dir: np.ndarray, rotations: np.ndarray, permutations: np.ndarray,
                          reference: np.ndarray = REFERENCE_VIEW) -> np.ndarray:
    """(9,) int: the keypoint permutation of the symmetric pose whose camera direction lies
    nearest to ``reference`` (:func:`canonical_index`).

    Corner k of pose ``R S`` projects where corner ``perm[k]`` of pose ``R`` does, so the
    relabelled keypoints are ``keypoints[perm]``. A NaN ``view_dir`` keeps the identity.
    """
    k = canonical_index(view_dir, rotations, reference)
    return np.arange(NUM_KEYPOINTS) if k is None else permutations[k]


def canonical_rotation(R: np.ndarray, t: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(3, 3) ``R S``: the symmetric-equivalent rotation of pose (R, t) whose projected cuboid
    is the canonically relabelled one (``R`` itself for a NaN view)."""
    k = canonical_index(camera_direction(R, t), rotations)
    return np.asarray(R, dtype=np.float64) if k is None else np.asarray(R, dtype=np.float64) @ rotations[k]


def canonical_keypoints(keypoints: np.ndarray, view_dirs: np.ndarray, rotations: np.ndarray,
                        permutations: np.ndarray) -> np.ndarray:
    """Relabel (I, 9, 2) projected keypoints of I instances given their (I, 3) camera directions."""
    kp = np.asarray(keypoints)
    out = kp.copy()
    for i in range(len(kp)):
        out[i] = kp[i][canonical_permutation(view_dirs[i], rotations, permutations)]
    return out
