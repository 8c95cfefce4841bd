"""Symmetry transforms: what the BOP symmetry fields and the HOPE categories mean as rigid
transforms of the model frame (``x' = T[:3, :3] x + T[:3, 3]``, identity first).

- :func:`symmetries_from_models_info`: a ``models_info.json`` entry (or a declaration)
  discretized exactly as the BOP toolkit does (``misc.get_symmetry_transformations``): the
  evaluation's and BOP19 scoring's symmetries.
- :func:`symmetry_transforms` / :func:`declaration_transforms`: the same fields sampled every
  ``step_deg`` (90 degrees gives the turns that can permute cuboid corners: training labels).
- :func:`category_symmetries`: the symmetry group of a HOPE catalog category.
- :func:`centred_symmetries`: a group about a box centre instead of the origin.

The fields themselves are read (and checked) by :func:`dope_hope.io.bop.parse_symmetries`.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.catalog import CATEGORIES
from dope_hope.errors import UnknownObjectError
from dope_hope.io.bop import parse_model_info, parse_symmetries
from dope_hope.io.jsonfields import JsonFields
from dope_hope.io.symmetries import SymmetryDeclaration


def _axis_rotation(angle: float, axis: np.ndarray) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (rad) about ``axis`` (normalized here), with the
    operations of the BOP toolkit's ``transform.rotation_matrix`` (Gohlke's transformations)."""
    sina, cosa = math.sin(angle), math.cos(angle)
    d = np.array(axis[:3], dtype=np.float64, copy=True)
    d /= math.sqrt(np.dot(d, d))
    R = np.diag([cosa, cosa, cosa])
    R += np.outer(d, d) * (1.0 - cosa)
    d *= sina
    R += np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    return R


def compose_symmetries(discrete: Sequence[np.ndarray],
                       continuous: Sequence[tuple[np.ndarray, np.ndarray]], steps: int) -> np.ndarray:
    """Discrete symmetries combined with discretized continuous ones, as the BOP toolkit's
    ``get_symmetry_transformations`` builds them (same operations, so the same numbers).

    Args:
        discrete: (4, 4) model-frame transforms, the identity NOT included (it is put first
            here); used as given.
        continuous: (axis (3,), offset (3,)) rotational symmetries, lengths in the unit of the
            discrete translations; each is sampled at ``k * 2 pi / steps``, k = 0 .. steps - 1
            (so the identity is kept), about the axis through ``offset``.
        steps: rotations per continuous symmetry.

    Returns:
        (S, 4, 4) float, identity first: each discrete symmetry (identity included) composed
        with each continuous rotation, ``R = R_c R_d``, ``t = R_c t_d + t_c``; just the
        discrete ones when no continuous rotation is sampled.
    """
    discrete = [np.eye(4)] + [np.asarray(D, dtype=np.float64) for D in discrete]
    rotations = []
    for axis, offset in continuous:
        step = 2.0 * np.pi / steps
        offset = np.asarray(offset, dtype=np.float64).reshape((3, 1))
        for i in range(steps):
            R = _axis_rotation(i * step, np.asarray(axis, dtype=np.float64))
            rotations.append((R, -R.dot(offset) + offset))
    if not rotations:
        return np.stack(discrete)
    out = []
    for D in discrete:
        R_d, t_d = D[:3, :3], D[:3, 3].reshape((3, 1))
        for R_c, t_c in rotations:
            T = np.eye(4)
            T[:3, :3] = R_c.dot(R_d)
            T[:3, 3:] = R_c.dot(t_d) + t_c
            out.append(T)
    return np.stack(out)


def symmetry_transforms(info: dict, step_deg: float = 1.0) -> np.ndarray:
    """All symmetry transforms of a model (from :func:`parse_model_info`), metres.

    Continuous symmetries (rotation about ``axis`` through ``offset``) are sampled every
    ``step_deg`` (at most; the step divides 360°) and composed with the discrete ones by
    :func:`compose_symmetries`; discrete entries equal to the identity are dropped.

    Returns:
        (S, 4, 4) float, identity first: ``x' = T[:3, :3] x + T[:3, 3]``.
    """
    discrete = [T for T in info.get("symmetries_discrete", []) if not np.allclose(T, np.eye(4))]
    steps = max(1, int(np.ceil(360.0 / step_deg)))
    return compose_symmetries(discrete, info.get("symmetries_continuous", []), steps)


def declaration_transforms(declaration: SymmetryDeclaration, step_deg: float = 1.0) -> np.ndarray:
    """(S, 4, 4) model-frame transforms of a declaration, metres, identity first; continuous
    symmetries sampled every ``step_deg`` (90 gives the ones that can permute cuboid corners)."""
    info = parse_model_info(JsonFields(declaration.source), declaration.entry, "", declaration.units)
    return symmetry_transforms(info, step_deg)


def symmetries_from_models_info(info: dict[str, Any], max_sym_disc_step: float = 0.01,
                                unit: float = 0.001, source: str | os.PathLike = "models_info.json",
                                where: str = "") -> np.ndarray:
    """Symmetry transforms of one BOP ``models_info.json`` entry (or a symmetry declaration,
    :mod:`dope_hope.io.symmetries`), as the BOP toolkit builds them
    (``misc.get_symmetry_transformations``, same operations).

    ``symmetries_discrete``: 4x4 row-major lists (R used as stored), translation in the file's
    unit. ``symmetries_continuous``: ``{"axis": [x, y, z], "offset": [x, y, z]}``,
    discretized into ``ceil(pi / max_sym_disc_step)`` rotations about the axis through
    ``offset`` (so the point farthest from the axis moves at most ``max_sym_disc_step`` x
    diameter per step); each discrete symmetry (identity included) is combined with each of
    these rotations (:func:`compose_symmetries`). The fields are read by
    :func:`dope_hope.io.bop.parse_symmetries`.

    Args:
        unit: output units per file unit: 0.001 -> metres from millimetres (default), 1.0 ->
            the file's numbers exactly (BOP19 scoring).
        source, where: the file and entry, for error messages.

    Returns:
        (S, 4, 4) float, identity first.

    Raises:
        InputFileError: a malformed symmetry field (named with ``source`` and ``where``).
    """
    discrete, continuous = parse_symmetries(JsonFields(source), info, where)
    steps = int(np.ceil(np.pi / max_sym_disc_step)) if continuous else 0
    out = compose_symmetries(discrete, continuous, steps)
    if unit != 1.0:
        out[:, :3, 3] *= unit
    return out


def _rigid(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def category_symmetries(category: str, step_deg: float = 1.0) -> np.ndarray:
    """Geometric symmetry group of a HOPE category as model-frame transforms.

    cylinder: rotation about the vertical (y) axis in ``step_deg`` steps, combined with the
    180° top-bottom flip (about x); cuboid: identity and the 180° flips about x, y and z;
    bottle: identity and the 180° front-back flip (about the vertical y axis).

    Returns:
        (S, 4, 4) float, identity first; rotations about the model origin (the HOPE meshes
        are centred on their bounding box).
    """
    if category == "cylinder":
        angles = np.arange(0.0, 360.0, step_deg)
        about_y = Rotation.from_euler("y", angles[:, None], degrees=True)
        flip = Rotation.from_euler("x", 180, degrees=True)
        rots = np.concatenate([about_y.as_matrix(), (about_y * flip).as_matrix()])
    elif category == "cuboid":
        rots = np.stack([np.eye(3)] + [Rotation.from_euler(a, 180, degrees=True).as_matrix()
                                       for a in "xyz"])
    elif category == "bottle":
        rots = np.stack([np.eye(3), Rotation.from_euler("y", 180, degrees=True).as_matrix()])
    else:
        raise UnknownObjectError(f"unknown category {category!r}; known: {', '.join(CATEGORIES)}")
    return np.stack([_rigid(R) for R in rots])


def centred_symmetries(syms: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Symmetries about ``center`` (3,) instead of the origin: ``T(c) S T(-c)``; (S, 4, 4)."""
    if np.allclose(center, 0.0, atol=1e-6):
        return syms
    T = np.eye(4)
    T[:3, 3] = center
    Ti = np.eye(4)
    Ti[:3, 3] = -center
    return np.einsum("ij,sjk,kl->sil", T, syms, Ti)
