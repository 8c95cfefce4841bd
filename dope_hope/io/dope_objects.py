"""The objects of a DOPE-format annotation in each of its four variants, read into metres
(:func:`read_objects`; :func:`detect_variant` tells the variant of a parsed document). The
file around them (camera, sibling images, writing) is :mod:`dope_hope.io.dope_json`'s.

**project** (``"format": "dope-hope"``, :mod:`dope_hope.io.dope_json` writes it): ``location``
in the file's ``units``, ``quaternion_xyzw`` the mesh-frame pose (``x_c = R x + t``),
``keypoint_order`` per file or per object.

**NDDS/FAT** (the official DOPE training samples; no ``format`` key): location in cm,
``quaternion_xyzw`` in NDDS's left-handed (Unreal) convention, ``camera_data`` usually empty
(K None; a sibling ``_camera_settings.json`` is used when present), keypoints in the current
order. The reader converts the quaternion so that ``R`` is the pose of the frame in which the
projected cuboid is the axis-aligned box of :data:`~dope_hope.geometry.CUBOID_CORNER_SIGNS`:
``R = R((-qz, qy, -qx, qw)) @ diag(-1, -1, 1)``. Verified on the official samples: PnP on
``projected_cuboid`` with the FAT camera (fx = fy = 768.16, cx = cy = 256) and the cracker
box gives this R to 1e-6 and t equal to ``location``. When K is known the reader checks
both this R and the quaternion taken as is against the projected cuboid and keeps the one
that fits (files of other generators in this layout use a right-handed quaternion). Raw
NDDS/FAT exports list 8 corners in ``projected_cuboid`` and the centre in
``projected_cuboid_centroid``; the two are joined, as the official DOPE loader does. The
cuboid sizes of a folder's classes are in its ``_object_settings.json``
(:func:`dope_hope.io.dope_json.read_ndds_object_settings`).

**BlenderProc** (the official generator ``data_generation/blenderproc_data_gen``: a
``camera_data.camera_look_at`` without NViSII's ``camera_view_matrix``): ``visibility`` is the
object's visible pixel count (``ObjectAnnotation.visible_pixels``; its fraction is unknown),
``location`` (cm) and ``quaternion_xyzw`` are the mesh-frame pose in Blender's camera frame
(x right, y up, z backwards), turned here into the OpenCV frame with ``diag(1, -1, -1)``. Its
``projected_cuboid`` lists Blender's bounding-box corners with the y signs of the current
order flipped (the generator's ``dope_order``); the reader renumbers them into the current
order (corners 0..7 <- 3, 2, 1, 0, 7, 6, 5, 4) after checking against the pose, when K is
known, which numbering the points fit. Generator versions before mid-2024 wrote ``K[2][0]``,
``K[2][1]`` (zeros) as ``cx``, ``cy``: :func:`dope_hope.io.dope_json.read_dope_json` does not
use such intrinsics (K None).

**NViSII** (``local_to_world_matrix`` per object, ``camera_view_matrix``): metres. Its
``quaternion_xyzw`` is wrong for scaled objects, so R is rebuilt from the two matrices (both
stored transposed: translation in the last row) and the scale removed with
:func:`~dope_hope.geometry.nearest_rotation`. The exporter writes the legacy keypoint order
(corner k at ``L @ signs_k`` in the object frame); the reader checks which order the cuboid
fits (from ``local_cuboid`` when present, else by fitting the box to ``projected_cuboid`` with
the rebuilt R and K, up to scale) and records it in ``keypoint_order``.

Its ``bounding_box_minx_maxx_miny_maxy`` has y one pixel too low (checked against the
segmentation masks); the reader corrects it.

**Visibility.** A fraction in [0, 1]; a larger whole number is read as a pixel count (the
BlenderProc convention, also when a file of another layout copies it), anything else is an
error. A BlenderProc file's ``visibility`` is always a count.
"""
from __future__ import annotations

import math

import numpy as np

from dope_hope.annotation import ObjectAnnotation
from dope_hope.geometry import (
    CUBOID_CORNER_SIGNS,
    KEYPOINT_ORDER,
    LEGACY_KEYPOINT_ORDER,
    LEGACY_TO_MESH,
    NUM_KEYPOINTS,
    UNIT_SCALE,
    nearest_rotation,
    project_points,
    quaternion_xyzw_to_matrix,
)
from dope_hope.io.jsonfields import JsonFields

FORMAT_NAME = "dope-hope"
_KEYPOINT_ORDERS = (KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER)
#: Corner sign patterns, in the object's own frame, of each keypoint order.
ORDER_CORNER_SIGNS: dict[str, np.ndarray] = {
    KEYPOINT_ORDER: CUBOID_CORNER_SIGNS,
    LEGACY_KEYPOINT_ORDER: CUBOID_CORNER_SIGNS @ LEGACY_TO_MESH.T,
}
# NDDS (Unreal, left-handed) quaternion -> right-handed cuboid frame: components remapped
# (x, y, z) -> (-z, y, -x), then the fixed 180° turn about z of the current keypoint order.
_NDDS_QUAT_INDEX = [2, 1, 0, 3]
_NDDS_QUAT_SIGN = np.array([-1.0, 1.0, -1.0, 1.0])
_NDDS_FRAME = np.diag([-1.0, -1.0, 1.0])
#: Blender's camera frame (x right, y up, z backwards) -> OpenCV's.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
#: The BlenderProc generator's corner k is the current order's corner _BLENDERPROC_CORNERS[k]
#: (its labels have the current order's y signs flipped; an involution).
_BLENDERPROC_CORNERS = np.array([3, 2, 1, 0, 7, 6, 5, 4, 8])
#: Largest reprojection error (px) of a corner numbering that is taken to fit a pose.
_ORDER_FIT_PX = 1.0


# --------------------------------------------------------------------------- objects
def _projected_cuboid(f: JsonFields, o: dict, where: str) -> np.ndarray | None:
    """(9, 2) pixels; NDDS's 8 corners + ``projected_cuboid_centroid`` are joined."""
    value = o.get("projected_cuboid")
    if value is None:
        return None
    if (isinstance(value, list) and len(value) == NUM_KEYPOINTS - 1
            and o.get("projected_cuboid_centroid") is not None):
        corners = f.array(value, f"{where}.projected_cuboid", (NUM_KEYPOINTS - 1, 2))
        centre = f.array(o["projected_cuboid_centroid"], f"{where}.projected_cuboid_centroid", (2,))
        return np.vstack([corners, centre[None]])
    return f.array(value, f"{where}.projected_cuboid", (NUM_KEYPOINTS, 2))


def _pixel_count(f: JsonFields, value: float, field: str) -> int:
    if value < 0 or value != int(value):
        raise f.fail(field, f"expected a visible pixel count (a whole number >= 0), got {value}")
    return int(value)


def _visibility(f: JsonFields, o: dict, where: str, counts: bool) -> tuple[float | None, int | None]:
    """(fraction, pixel count) of ``visibility``; ``counts``: the variant writes pixel counts."""
    field = f"{where}.visibility"
    if o.get("visibility") is None:
        return None, None
    vis = f.number(o["visibility"], field)
    if counts:
        return None, _pixel_count(f, vis, field)
    if 0.0 <= vis <= 1.0:
        return vis, None
    if vis > 1.0 and vis == int(vis):
        return None, int(vis)
    raise f.fail(field, f"expected a fraction in [0, 1] or a visible pixel count, got {vis}")


def _common_fields(f: JsonFields, o: dict, where: str, pixel_counts: bool = False) -> dict:
    """class, projected_cuboid, visibility shared by all variants."""
    cls = f.get(o, "class", where)
    if not isinstance(cls, str) or not cls:
        raise f.fail(f"{where}.class", f"expected a non-empty string, got {cls!r}")
    vis, pixels = _visibility(f, o, where, pixel_counts)
    if pixels is None and o.get("visible_pixels") is not None:
        pixels = _pixel_count(f, f.number(o["visible_pixels"], f"{where}.visible_pixels"),
                              f"{where}.visible_pixels")
    return {"class_name": cls, "projected_cuboid": _projected_cuboid(f, o, where),
            "visibility": vis, "visible_pixels": pixels}


def _bbox_top_left(f: JsonFields, o: dict, where: str) -> np.ndarray | None:
    box = o.get("bounding_box")
    if box is None:
        return None
    if not isinstance(box, dict):
        raise f.fail(f"{where}.bounding_box", "expected {'top_left': [u, v], 'bottom_right': [u, v]}")
    tl = f.array(f.get(box, "top_left", f"{where}.bounding_box"), f"{where}.bounding_box.top_left", (2,))
    br = f.array(f.get(box, "bottom_right", f"{where}.bounding_box"),
                 f"{where}.bounding_box.bottom_right", (2,))
    return np.concatenate([tl, br])


def _instance_id(f: JsonFields, o: dict, where: str, key: str) -> int | None:
    v = o.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v):
        raise f.fail(f"{where}.{key}", f"expected an integer, got {v!r}")
    return int(v)


def _pose_from_location_quaternion(f: JsonFields, o: dict, where: str, scale: float):
    loc = f.array(f.get(o, "location", where), f"{where}.location", (3,))
    q = f.array(f.get(o, "quaternion_xyzw", where), f"{where}.quaternion_xyzw", (4,))
    if np.linalg.norm(q) < 1e-8:
        raise f.fail(f"{where}.quaternion_xyzw", "zero quaternion")
    return quaternion_xyzw_to_matrix(q), loc * scale


def _read_project_objects(f: JsonFields, data: dict) -> list[ObjectAnnotation]:
    units = data.get("units", "cm")
    if units not in UNIT_SCALE:
        raise f.fail("units", f"expected one of {sorted(UNIT_SCALE)}, got {units!r}")
    default_order = data.get("keypoint_order", KEYPOINT_ORDER)
    out = []
    for i, o in enumerate(_objects_list(f, data)):
        where = f"objects[{i}]"
        common = _common_fields(f, o, where)
        R, t = _pose_from_location_quaternion(f, o, where, UNIT_SCALE[units])
        order = o.get("keypoint_order", default_order)
        if order not in _KEYPOINT_ORDERS:
            raise f.fail(f"{where}.keypoint_order", f"expected one of {_KEYPOINT_ORDERS}, got {order!r}")
        out.append(ObjectAnnotation(R=R, t=t, bbox_xyxy=_bbox_top_left(f, o, where),
                                    instance_id=_instance_id(f, o, where, "instance_id"),
                                    keypoint_order=order, **common))
    return out


def _read_ndds_objects(f: JsonFields, data: dict, K: np.ndarray | None) -> list[ObjectAnnotation]:
    out = []
    for i, o in enumerate(_objects_list(f, data)):
        where = f"objects[{i}]"
        common = _common_fields(f, o, where)
        R_raw, t = _pose_from_location_quaternion(f, o, where, 0.01)
        q = np.asarray(o["quaternion_xyzw"], dtype=np.float64)
        R = quaternion_xyzw_to_matrix(q[_NDDS_QUAT_INDEX] * _NDDS_QUAT_SIGN) @ _NDDS_FRAME
        uv = common["projected_cuboid"]
        if K is not None and uv is not None:
            # other generators write this layout with a right-handed quaternion: keep the
            # rotation whose box fits the projected cuboid
            signs = ORDER_CORNER_SIGNS[KEYPOINT_ORDER]
            if fit_cuboid_up_to_scale(uv, K, R_raw, signs)[0] < fit_cuboid_up_to_scale(uv, K, R, signs)[0]:
                R = R_raw
        # NDDS "bounding_box" corners are (row, col) in some exporters and (x, y) in others:
        # ambiguous, so left out rather than guessed.
        out.append(ObjectAnnotation(R=R, t=t, keypoint_order=KEYPOINT_ORDER,
                                    instance_id=_instance_id(f, o, where, "instance_id"), **common))
    return out


def _read_blenderproc_objects(f: JsonFields, data: dict, K: np.ndarray | None) -> list[ObjectAnnotation]:
    out = []
    for i, o in enumerate(_objects_list(f, data)):
        where = f"objects[{i}]"
        common = _common_fields(f, o, where, pixel_counts=True)
        R_gl, t_gl = _pose_from_location_quaternion(f, o, where, 0.01)
        R, t = _GL_TO_CV @ R_gl, _GL_TO_CV @ t_gl
        uv = common["projected_cuboid"]
        order = KEYPOINT_ORDER
        if uv is not None:
            renumbered = uv[_BLENDERPROC_CORNERS]
            if K is not None:
                # which numbering the points fit under the pose (the generator's, or a tool
                # writing one of the known orders in this layout)
                fits = [(fit_cuboid_up_to_scale(renumbered, K, R, CUBOID_CORNER_SIGNS)[0],
                         KEYPOINT_ORDER, renumbered)]
                fits += [(fit_cuboid_up_to_scale(uv, K, R, signs)[0], name, uv)
                         for name, signs in ORDER_CORNER_SIGNS.items()]
                err, order, renumbered = min(fits, key=lambda x: x[0])
                if err > _ORDER_FIT_PX:
                    raise f.fail(f"{where}.projected_cuboid",
                                 f"fits the pose in no known corner order (best {err:.1f} px off)")
            common["projected_cuboid"] = renumbered
        out.append(ObjectAnnotation(R=R, t=t, keypoint_order=order, **common))
    return out


def _objects_list(f: JsonFields, data: dict) -> list:
    objs = data.get("objects", [])
    if objs is None:
        objs = []
    if not isinstance(objs, list):
        raise f.fail("objects", f"expected a list, got {type(objs).__name__}")
    for i, o in enumerate(objs):
        if not isinstance(o, dict):
            raise f.fail(f"objects[{i}]", f"expected an object, got {type(o).__name__}")
    return objs


# --------------------------------------------------------------------------- NViSII
def _as_column_major(M: np.ndarray, transposed: bool | None) -> tuple[np.ndarray, bool]:
    """A 4x4 rigid/affine matrix in column-vector form; detects NViSII's transposed storage."""
    if transposed is None:
        has_row_t = not np.allclose(M[3, :3], 0.0)
        has_col_t = not np.allclose(M[:3, 3], 0.0)
        transposed = has_row_t or not has_col_t  # exporter default: transposed
    return (M.T if transposed else M), transposed


def fit_cuboid_up_to_scale(uv: np.ndarray, K: np.ndarray, R: np.ndarray,
                           signs: np.ndarray) -> tuple[float, np.ndarray]:
    """Fit an axis-aligned box with rotation R to 9 projected keypoints, scale unknown.

    Unknowns: the box centre in the camera frame p (3,) and half-extents h (3,); keypoint k is
    ``p + R (signs_k * h)`` (k = 8: p). The projection constraints are linear and homogeneous
    in (p, h), so the fit is the SVD null vector; the scale is irrelevant to the reprojection.
    A fit that needs a negative half-extent is the mirror image of the numbering (its corners
    with one axis's signs flipped) and does not count.

    Args:
        uv: (9, 2) pixels; K: (3, 3); R: (3, 3) object -> camera; signs: (8, 3) corner signs.

    Returns:
        (max reprojection error in pixels (inf if the fit puts points behind the camera or
        needs a negative extent), (9, 3) fitted camera-frame points at an arbitrary scale).
    """
    rows = []
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for k in range(NUM_KEYPOINTS):
        D = np.hstack([np.eye(3), R @ np.diag(signs[k]) if k < 8 else np.zeros((3, 3))])
        u, v = uv[k]
        rows.append((u - cx) * D[2] - fx * D[0])
        rows.append((v - cy) * D[2] - fy * D[1])
    y = np.linalg.svd(np.asarray(rows))[2][-1]
    p, h = y[:3], y[3:]
    if p[2] < 0:
        p, h = -p, -h
    pts = np.vstack([p + (R @ (signs * h).T).T, p[None]])
    if np.any(pts[:, 2] <= 0) or np.any(h < -1e-6 * np.abs(h).max()):
        return math.inf, pts
    return float(np.abs(project_points(pts, K) - uv).max()), pts


def _nvisii_order(f: JsonFields, o: dict, where: str, uv: np.ndarray | None, K: np.ndarray | None,
                  R: np.ndarray) -> str:
    local = o.get("local_cuboid")
    if local is not None:
        pts = f.array(local, f"{where}.local_cuboid", (NUM_KEYPOINTS, 3))
        s = np.sign(np.round(pts[:8] - pts[8], 9))
        for order, signs in ORDER_CORNER_SIGNS.items():
            # a degenerate (flat) box leaves zeros: compare on the non-zero axes only
            if np.all((s == signs) | (s == 0)):
                return order
        raise f.fail(f"{where}.local_cuboid", "corners follow neither the current nor the legacy order")
    if uv is None or K is None:
        return LEGACY_KEYPOINT_ORDER  # what the official NViSII exporter writes
    errs = {order: fit_cuboid_up_to_scale(uv, K, R, signs)[0]
            for order, signs in ORDER_CORNER_SIGNS.items()}
    best = min(errs, key=errs.get)
    return best if errs[best] < 1.0 else LEGACY_KEYPOINT_ORDER


def _read_nvisii_objects(f: JsonFields, data: dict, K: np.ndarray | None) -> list[ObjectAnnotation]:
    camera = data.get("camera_data") or {}
    V = None
    if camera.get("camera_view_matrix") is not None:
        V = f.array(camera["camera_view_matrix"], "camera_data.camera_view_matrix", (4, 4),
                    "rows", "columns")
    out = []
    for i, o in enumerate(_objects_list(f, data)):
        where = f"objects[{i}]"
        common = _common_fields(f, o, where)
        if o.get("local_to_world_matrix") is None or V is None:
            # no matrices: fall back on the exported pose (metres)
            R, t = _pose_from_location_quaternion(f, o, where, 1.0)
        else:
            M_raw = f.array(o["local_to_world_matrix"], f"{where}.local_to_world_matrix", (4, 4),
                            "rows", "columns")
            M, transposed = _as_column_major(M_raw, None)
            V_cm, _ = _as_column_major(V, transposed if np.allclose(V[3, :3], 0) and
                                       np.allclose(V[:3, 3], 0) else None)
            A = V_cm[:3, :3] @ M[:3, :3]  # object -> camera, with the object's scale
            t = V_cm[:3, :3] @ M[:3, 3] + V_cm[:3, 3]
            if o.get("location") is not None:
                loc = f.array(o["location"], f"{where}.location", (3,))
                flip = np.diag([1.0, -1.0, -1.0])  # OpenGL camera -> OpenCV, if not applied
                if np.linalg.norm(flip @ t - loc) < np.linalg.norm(t - loc):
                    A, t = flip @ A, flip @ t
            if abs(np.linalg.det(A)) < 1e-12:
                raise f.fail(f"{where}.local_to_world_matrix", "singular (zero scale)")
            R = nearest_rotation(A)
        order = _nvisii_order(f, o, where, common["projected_cuboid"], K, R)
        bbox = None
        if o.get("bounding_box_minx_maxx_miny_maxy") is not None:
            b = f.array(o["bounding_box_minx_maxx_miny_maxy"],
                        f"{where}.bounding_box_minx_maxx_miny_maxy", (4,))
            # the exporter's y range is one pixel too low in the image (checked against the
            # .seg.exr masks, which align with the RGB): shift it back
            bbox = b[[0, 2, 1, 3]] - [0.0, 1.0, 0.0, 1.0]
        out.append(ObjectAnnotation(R=R, t=t, bbox_xyxy=bbox, keypoint_order=order,
                                    instance_id=_instance_id(f, o, where, "segmentation_id"),
                                    **common))
    return out


def detect_variant(data: dict) -> str:
    """"project", "nvisii", "blenderproc" or "ndds" for a parsed DOPE JSON document."""
    if data.get("format") == FORMAT_NAME:
        return "project"
    camera = data.get("camera_data")
    objs = data.get("objects") if isinstance(data.get("objects"), list) else []
    if (isinstance(camera, dict) and "camera_view_matrix" in camera) or any(
            isinstance(o, dict) and ("local_to_world_matrix" in o or o.get("provenance") == "nvisii")
            for o in objs):
        return "nvisii"
    if isinstance(camera, dict) and "camera_look_at" in camera:
        return "blenderproc"
    return "ndds"


def read_objects(f: JsonFields, data: dict, variant: str, K: np.ndarray | None) -> list[ObjectAnnotation]:
    """The ``objects`` of a parsed document of ``variant`` (:func:`detect_variant`), metres.

    Args:
        f: the file's field reader (errors name the file and the field).
        data: the parsed document. K: (3, 3) intrinsics, or None when unknown (the corner
            numbering and NDDS's quaternion convention are then taken as written).

    Raises:
        InputFileError: a missing or malformed field, named.
    """
    if variant == "project":
        return _read_project_objects(f, data)
    if variant == "nvisii":
        return _read_nvisii_objects(f, data, K)
    if variant == "blenderproc":
        return _read_blenderproc_objects(f, data, K)
    return _read_ndds_objects(f, data, K)
