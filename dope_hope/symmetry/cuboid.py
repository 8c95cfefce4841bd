"""The symmetries of a cuboid: the rotations that map an object's box onto itself.

A network that sees only an object's cuboid (the pretrained start, trained with
category-canonical labels) cannot tell apart the poses ``R`` and ``R S`` for a rotation ``S``
of this group: a box of three different extents has the 180° turns about x, y and z; a
square cross-section adds the 90° turns about its axis; a cube has all 24 turns of the cube
group. :func:`cuboid_rotations` lists them in the mesh frame (about the box centre), and
:func:`describe_rotation` names one for a person ("180° about y").
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.geometry import CUBOID_CORNER_SIGNS

#: Extents closer than this fraction of the larger one count as equal (a square section).
EQUAL_EXTENT_TOL = 0.02
#: An extent this many times both others makes its axis the box's long axis (a can's, a bottle's).
LONG_AXIS_FACTOR = 1.3


def _cube_group() -> np.ndarray:
    """(24, 3, 3) the proper rotations among the signed permutation matrices, identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    out.sort(key=lambda M: (not np.array_equal(M, np.eye(3)),))
    return np.stack(out)


CUBE_GROUP = _cube_group()


def cuboid_rotations(size_m: np.ndarray, tol: float = EQUAL_EXTENT_TOL) -> np.ndarray:
    """(S, 3, 3) rotations about the box centre that map a box of ``size_m`` (3,) extents onto
    itself (mesh frame), identity first: 4 for three different extents, 8 for a square
    section, 24 for a cube."""
    size = np.asarray(size_m, dtype=np.float64).reshape(3)
    keep = [M for M in CUBE_GROUP if np.all(np.abs(np.abs(M) @ size - size) <= tol * size.max())]
    return np.stack(keep)


def long_axis(size_m: np.ndarray, factor: float = LONG_AXIS_FACTOR) -> int | None:
    """The axis (0, 1, 2: x, y, z) whose extent in ``size_m`` (3,) exceeds ``factor`` times
    both others (a can's or bottle's axis, a tall box's), else None."""
    size = np.asarray(size_m, dtype=np.float64).reshape(3)
    k = int(np.argmax(size))
    return k if np.all(size[k] > factor * np.delete(size, k)) else None


def nearest_cube_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation of the cube group (the 24 rotations mapping the axes onto the axes)
    nearest (3, 3) ``R`` (Frobenius norm; the first of equals)."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    return CUBE_GROUP[int(np.argmin(np.linalg.norm(CUBE_GROUP - R, axis=(1, 2))))].copy()


def corner_permutation(S: np.ndarray) -> np.ndarray:
    """(9,) int ``perm`` of a rotation S of :func:`cuboid_rotations`: corner k of the pose
    ``R S`` is corner ``perm[k]`` of the pose ``R`` (keypoints (9, 2) of R become those of
    ``R S`` as ``keypoints[perm]``); the centre stays."""
    signs = CUBOID_CORNER_SIGNS @ np.rint(np.asarray(S, dtype=np.float64)).T
    order = [int(np.flatnonzero(np.all(CUBOID_CORNER_SIGNS == m, axis=1))[0]) for m in signs]
    return np.array(order + [len(CUBOID_CORNER_SIGNS)])


def describe_rotation(S: np.ndarray) -> str:
    """A person's name of a rotation of the cube group: "identity", "180° about y",
    "90° about -z" (right-handed), or an axis of the form "120° about (1, 1, 1)"."""
    rotvec = Rotation.from_matrix(np.asarray(S, dtype=np.float64)).as_rotvec()
    angle = float(np.degrees(np.linalg.norm(rotvec)))
    if angle < 1e-6:
        return "identity"
    axis = rotvec / np.linalg.norm(rotvec)
    if angle > 179.999:  # the sign of a half turn's axis is arbitrary: name it positive
        axis = axis * (1.0 if axis[np.argmax(np.abs(axis) > 1e-6)] > 0 else -1.0)
    nonzero = np.flatnonzero(np.abs(axis) > 1e-6)
    if len(nonzero) == 1:
        name = ("-" if axis[nonzero[0]] < 0 else "") + "xyz"[nonzero[0]]
    else:
        unit = axis / np.abs(axis[nonzero]).min()
        name = "(" + ", ".join(f"{v:g}" for v in np.round(unit, 3)) + ")"
    return f"{angle:.0f}° about {name}"
