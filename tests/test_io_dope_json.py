"""dope_hope.io.dope_json: the three DOPE JSON variants, the writer, frame listing, errors."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from json_edit import with_field
from scipy.spatial.transform import Rotation

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.errors import DopeHopeError, InputFileError
from dope_hope.geometry import (
    CUBOID_CORNER_SIGNS,
    LEGACY_TO_MESH,
    cuboid_keypoints,
    intrinsics_matrix,
    legacy_keypoints_to_current,
    project_points,
    quaternion_xyzw_to_matrix,
    rotation_error_deg,
)
from dope_hope.io.dope_json import (
    list_dope_frames,
    read_dope_json,
    read_frame_depth_m,
    read_ndds_object_settings,
    recorded_cuboid_size,
    write_dope_json,
)
from dope_hope.io.dope_objects import ORDER_CORNER_SIGNS, fit_cuboid_up_to_scale
from dope_hope.io.images import read_depth_m, read_image_raw
from dope_hope.io.meshes import load_mesh, mesh_cuboid

# The official DOPE NDDS samples were rendered with the FAT camera (512 x 512 crop) and show
# the YCB cracker box; its cuboid size from the official DOPE config, centimetres.
FAT_K = intrinsics_matrix(768.16, 768.16, 256.0, 256.0)
CRACKER_SIZE_M = np.array([16.4036, 21.3437, 7.18]) / 100.0


@pytest.fixture(scope="module")
def ndds_dir(shared_data) -> Path:
    return shared_data / "dope_format_samples" / "ndds"


@pytest.fixture(scope="module")
def nvisii_json(shared_data) -> Path:
    return shared_data / "dope_format_samples" / "nvisii" / "00000.json"


@pytest.fixture(scope="module")
def nvisii_frame(nvisii_json) -> FrameAnnotation:
    return read_dope_json(nvisii_json)


@pytest.fixture(scope="module")
def ketchup_size(ketchup_obj):
    return mesh_cuboid(load_mesh(ketchup_obj))


# --------------------------------------------------------------------------- NDDS / FAT
def test_ndds_sample_values(ndds_dir):
    frames = list_dope_frames(ndds_dir)
    assert [p.name for p in frames] == ["000000.json", "000001.json", "000030.json", "000031.json"]
    fr = read_dope_json(frames[0])
    raw = json.loads(frames[0].read_text())["objects"][0]
    assert fr.K is None  # camera_data is empty
    assert (fr.width, fr.height) == (512, 512)  # from the image header
    assert fr.image_path == ndds_dir / "000000.png"
    assert fr.depth_path is None and fr.seg_path is None
    assert len(fr.objects) == 1
    o = fr.objects[0]
    assert o.class_name == "cracker"
    assert o.visibility == 1.0
    assert o.keypoint_order == "dope-current"
    np.testing.assert_allclose(o.t, [-0.0540710973739624, 0.1020408821105957, 0.5531976318359375])
    np.testing.assert_allclose(o.projected_cuboid, raw["projected_cuboid"])
    np.testing.assert_allclose(o.projected_cuboid[8], [180.91781616210938, 397.6921691894531])
    # identical JSON -> identical annotation
    o1 = read_dope_json(frames[1]).objects[0]
    np.testing.assert_array_equal(o1.R, o.R)
    np.testing.assert_array_equal(o1.t, o.t)


def test_ndds_pose_reprojects_the_cuboid(ndds_dir):
    """R is the cuboid-frame pose: the cracker box in the current order reprojects exactly."""
    kp = cuboid_keypoints(CRACKER_SIZE_M)
    for path in list_dope_frames(ndds_dir):
        o = read_dope_json(path).objects[0]
        err = np.abs(project_points(kp, FAT_K, o.R, o.t) - o.projected_cuboid).max()
        assert err < 0.01, path.name
        # and PnP on the file's keypoints recovers the same pose
        ok, rvec, tvec = cv2.solvePnP(kp, o.projected_cuboid, FAT_K, None)
        assert ok
        assert rotation_error_deg(cv2.Rodrigues(rvec)[0], o.R) < 1e-3
        np.testing.assert_allclose(tvec.ravel(), o.t, atol=1e-5)


def test_ndds_camera_settings_sibling(tmp_path, ndds_dir):
    for name in ("000030.json", "000030.png"):
        (tmp_path / name).write_bytes((ndds_dir / name).read_bytes())
    (tmp_path / "_camera_settings.json").write_text(json.dumps({"camera_settings": [{
        "name": "Viewpoint", "horizontal_fov": 64,
        "intrinsic_settings": {"fx": 768.16, "fy": 768.16, "cx": 256, "cy": 256, "s": 0},
        "captured_image_size": {"width": 512, "height": 512}}]}))
    fr = read_dope_json(tmp_path / "000030.json")
    np.testing.assert_allclose(fr.K, FAT_K)
    o = fr.objects[0]
    assert np.abs(project_points(cuboid_keypoints(CRACKER_SIZE_M), FAT_K, o.R, o.t)
                  - o.projected_cuboid).max() < 0.01
    assert list_dope_frames(tmp_path) == [tmp_path / "000030.json"]  # settings file skipped


def test_right_handed_quaternion_without_format_key_is_kept(tmp_path):
    """A file in this layout from another generator (intrinsics given, quaternion already
    right-handed) keeps its rotation: the reader checks which one fits the cuboid."""
    R = Rotation.from_euler("xyz", [20, -40, 65], degrees=True).as_matrix()
    t = np.array([0.05, -0.02, 0.7])
    kp = project_points(cuboid_keypoints([0.1, 0.2, 0.05]), FAT_K, R, t)
    path = tmp_path / "000000.json"
    path.write_text(json.dumps({
        "camera_data": {"intrinsics": {"fx": 768.16, "fy": 768.16, "cx": 256.0, "cy": 256.0}},
        "objects": [{"class": "box", "location": (t * 100).tolist(),
                     "quaternion_xyzw": Rotation.from_matrix(R).as_quat().tolist(),
                     "projected_cuboid": kp.tolist()}]}))
    o = read_dope_json(path).objects[0]
    assert rotation_error_deg(o.R, R) < 1e-6


def test_fat_eight_corners_and_centroid_are_joined(tmp_path, ndds_dir):
    """Raw NDDS/FAT exports list 8 corners plus ``projected_cuboid_centroid``."""
    data = json.loads((ndds_dir / "000000.json").read_text())
    o = data["objects"][0]
    o["projected_cuboid_centroid"] = o["projected_cuboid"][8]
    o["projected_cuboid"] = o["projected_cuboid"][:8]
    path = tmp_path / "000000.json"
    path.write_text(json.dumps(data))
    got = read_dope_json(path).objects[0].projected_cuboid
    np.testing.assert_array_equal(got, read_dope_json(ndds_dir / "000000.json").objects[0].projected_cuboid)


def _copy_ndds_frame(ndds_dir: Path, folder: Path, stem: str = "000000") -> Path:
    for suffix in (".json", ".png"):
        (folder / f"{stem}{suffix}").write_bytes((ndds_dir / f"{stem}{suffix}").read_bytes())
    return folder / f"{stem}.json"


def test_ndds_object_settings_give_the_cuboid_size(tmp_path, ndds_dir):
    """``_object_settings.json`` (cm, the annotations' object frame) is what a folder records."""
    path = _copy_ndds_frame(ndds_dir, tmp_path)
    assert recorded_cuboid_size(path, "cracker") is None
    (tmp_path / "_object_settings.json").write_text(json.dumps({
        "exported_object_classes": ["Cracker"],
        "exported_objects": [{"class": "Cracker", "segmentation_class_id": 255,
                              "fixed_model_transform": np.eye(4).tolist(),
                              "cuboid_dimensions": (CRACKER_SIZE_M * 100).tolist()}]}))
    assert list(read_ndds_object_settings(tmp_path / "_object_settings.json")) == ["Cracker"]
    np.testing.assert_allclose(recorded_cuboid_size(path, "cracker"), CRACKER_SIZE_M)
    assert recorded_cuboid_size(path, "mustard") is None
    # the size is the box the frame's keypoints show under its pose (FAT camera)
    o = read_dope_json(path).objects[0]
    assert np.abs(project_points(cuboid_keypoints(recorded_cuboid_size(path, "cracker")), FAT_K,
                                 o.R, o.t) - o.projected_cuboid).max() < 0.01
    assert list_dope_frames(tmp_path) == [path]  # the settings file is no frame
    (tmp_path / "_object_settings.json").write_text(json.dumps({"exported_objects": [
        {"class": "Cracker", "cuboid_dimensions": [16.4, -1, 7.2]}]}))
    with pytest.raises(InputFileError, match=r"_object_settings.json: exported_objects\[0\]\.cuboid_dimensions"):
        recorded_cuboid_size(path, "cracker")


def test_recorded_cuboid_size_is_read_from_the_frame(tmp_path):
    frame = FrameAnnotation(tmp_path / "000001.json", np.eye(3), 96, 72, [])
    write_dope_json(tmp_path / "000001.json", frame,
                    extra={"cuboid": {"class": "Ketchup", "size_m": [0.0645, 0.1486, 0.0434]}})
    np.testing.assert_allclose(recorded_cuboid_size(tmp_path / "000001.json", "ketchup"), [0.0645, 0.1486, 0.0434])
    assert recorded_cuboid_size(tmp_path / "000001.json", "Mustard") is None
    assert recorded_cuboid_size(tmp_path / "000000.json", "Ketchup") is None


@pytest.mark.parametrize("value, fraction, pixels", [
    (1.0, 1.0, None), (1, 1.0, None), (0.25, 0.25, None), (5234, None, 5234), (5234.0, None, 5234)])
def test_visibility_fraction_or_pixel_count(tmp_path, ndds_dir, value, fraction, pixels):
    """A fraction stays a fraction; a whole number above 1 is a visible pixel count."""
    data = json.loads((ndds_dir / "000000.json").read_text())
    data["objects"][0]["visibility"] = value
    path = tmp_path / "000000.json"
    path.write_text(json.dumps(data))
    o = read_dope_json(path).objects[0]
    assert (o.visibility, o.visible_pixels) == (fraction, pixels)
    # the project format keeps a count when no fraction is known
    write_dope_json(tmp_path / "copy.json", read_dope_json(path))
    back = read_dope_json(tmp_path / "copy.json").objects[0]
    assert (back.visibility, back.visible_pixels) == (fraction, pixels)


# --------------------------------------------------------------------------- BlenderProc
# Blender's bounding-box corner signs (bpy ``Object.bound_box`` order) and the official
# generator's ``dope_order`` (data_generation/blenderproc_data_gen/generate_training_data.py).
_BLENDER_BBOX_SIGNS = np.array([[-1, -1, -1], [-1, -1, 1], [-1, 1, 1], [-1, 1, -1],
                                [1, -1, -1], [1, -1, 1], [1, 1, 1], [1, 1, -1]], dtype=float)
_DOPE_ORDER = [6, 2, 1, 5, 7, 3, 0, 4]
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def _blenderproc_doc(R_cv: np.ndarray, t_cv_m: np.ndarray, size_m: np.ndarray, K: np.ndarray,
                     pixels: int = 5234, old_intrinsics: bool = False) -> dict:
    """One object as the official BlenderProc generator writes it (scene in cm; pose in
    Blender's camera frame; corners projected in its ``dope_order``)."""
    R_gl, t_gl = _GL_TO_CV @ R_cv, _GL_TO_CV @ t_cv_m * 100.0
    corners = _BLENDER_BBOX_SIGNS * size_m * 50.0  # cm, mesh frame
    cuboid = [None] * 9
    for ii in range(8):
        cuboid[_DOPE_ORDER[ii]] = project_points(corners[ii][None] * 0.01, K, R_cv, t_cv_m)[0]
    cuboid[8] = project_points(np.zeros((1, 3)), K, R_cv, t_cv_m)[0]
    cx, cy = (K[2, 0], K[2, 1]) if old_intrinsics else (K[0, 2], K[1, 2])
    return {"camera_data": {"width": 500, "height": 500,
                            "camera_look_at": {"at": [0, 1, 0], "eye": [0, 25, 0], "up": [1, 0, 0]},
                            "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": cx, "cy": cy}},
            "objects": [{"class": "Ketchup", "name": "Ketchup_000", "visibility": pixels,
                         "projected_cuboid": np.asarray(cuboid).tolist(),
                         "location": t_gl.tolist(),
                         "quaternion_xyzw": Rotation.from_matrix(R_gl).as_quat().tolist()}]}


def test_blenderproc_frame_is_read_in_the_current_order(tmp_path, ketchup_size):
    size, _ = ketchup_size
    K = intrinsics_matrix(603.55, 603.55, 249.5, 249.5)
    R = Rotation.from_euler("xyz", [30, -50, 120], degrees=True).as_matrix()
    t = np.array([0.04, -0.03, 0.62])
    path = tmp_path / "000000.json"
    path.write_text(json.dumps(_blenderproc_doc(R, t, size, K)))
    fr = read_dope_json(path)
    np.testing.assert_allclose(fr.K, K)
    o = fr.objects[0]
    assert (o.visibility, o.visible_pixels, o.keypoint_order) == (None, 5234, "dope-current")
    assert rotation_error_deg(o.R, R) < 1e-6
    np.testing.assert_allclose(o.t, t, atol=1e-9)
    # renumbered: the mesh box in the documented order reprojects onto the keypoints
    np.testing.assert_allclose(o.projected_cuboid, project_points(cuboid_keypoints(size), K, R, t), atol=1e-6)
    # the generator's own numbering is the mirror image: no box fits it under the pose
    raw = np.asarray(json.loads(path.read_text())["objects"][0]["projected_cuboid"])
    assert fit_cuboid_up_to_scale(raw, K, R, CUBOID_CORNER_SIGNS)[0] == np.inf
    # older generator versions wrote zeros for cx, cy: K unknown, same numbering
    path.write_text(json.dumps(_blenderproc_doc(R, t, size, K, old_intrinsics=True)))
    fr = read_dope_json(path)
    assert fr.K is None
    np.testing.assert_allclose(fr.objects[0].projected_cuboid, o.projected_cuboid)


def test_blenderproc_visibility_must_be_a_pixel_count(tmp_path, ketchup_size):
    K = intrinsics_matrix(600.0, 600.0, 250.0, 250.0)
    path = tmp_path / "000000.json"
    doc = _blenderproc_doc(np.eye(3), np.array([0.0, 0.0, 0.5]), ketchup_size[0], K)
    path.write_text(json.dumps(with_field(doc, "objects.0.visibility", 0.5)))
    with pytest.raises(InputFileError, match=r"objects\[0\]\.visibility: expected a visible pixel count"):
        read_dope_json(path)
    # keypoints that fit the pose in no known numbering are refused, not guessed
    doc["objects"][0]["projected_cuboid"][0] = [10.0, 10.0]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=r"projected_cuboid: fits the pose in no known corner order"):
        read_dope_json(path)


# --------------------------------------------------------------------------- NViSII
def test_nvisii_sample_values(nvisii_frame, nvisii_json):
    fr = nvisii_frame
    raw = json.loads(nvisii_json.read_text())
    np.testing.assert_allclose(fr.K, intrinsics_matrix(603.5535278320312, 603.5535278320312, 250, 250))
    assert (fr.width, fr.height) == (500, 500)
    assert fr.depth_path == nvisii_json.with_name("00000.depth.exr")
    assert fr.depth_scale_m == 1.0  # EXR depth is in metres
    assert fr.seg_path == nvisii_json.with_name("00000.seg.exr")
    assert fr.image_path == nvisii_json.with_name("00000.png")
    assert len(fr.objects) == len(raw["objects"]) == 22
    assert sum(o.class_name == "Ketchup" for o in fr.objects) == 14
    o, r = fr.objects[0], raw["objects"][0]
    assert o.class_name == "Melissa_Doug_Traffic_Signs_and_Vehicles"
    assert o.instance_id == 1
    # file: minx, maxx, miny, maxy = 0 109 1 117; its y is one pixel low (see the seg test)
    np.testing.assert_allclose(o.bbox_xyxy, [0, 0, 109, 116])
    np.testing.assert_allclose(o.t, r["location"], atol=1e-6)  # already metres
    assert fr.objects[3].visibility == pytest.approx(0.5770020533880903)
    for obj in fr.objects:
        assert obj.keypoint_order == "dope-legacy"
        np.testing.assert_allclose(obj.R @ obj.R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(obj.R) == pytest.approx(1.0)


def test_nvisii_siblings_agree_with_the_annotation(nvisii_frame):
    """seg.exr ids are the instance ids and give the boxes; depth.exr (ray distance) becomes
    z-depth that sits at each object's distance."""
    seg = read_image_raw(nvisii_frame.seg_path)[..., 0]
    z = read_frame_depth_m(nvisii_frame)
    ray = read_depth_m(nvisii_frame.depth_path)
    assert z.shape == seg.shape == (500, 500)
    assert np.all(z <= ray + 1e-6) and np.all(z >= 0)
    for o in nvisii_frame.objects:
        ys, xs = np.nonzero(seg == o.instance_id)
        assert len(xs) > 0
        np.testing.assert_array_equal(o.bbox_xyxy, [xs.min(), ys.min(), xs.max(), ys.max()])
        surface = np.median(z[ys, xs])
        assert abs(o.t[2] - surface) < 0.07  # visible surface within 7 cm of the centre's z
    # without the ray -> z conversion the depths would be off by up to ~25 cm
    k = next(o for o in nvisii_frame.objects if o.instance_id == 21)
    ys, xs = np.nonzero(seg == 21)
    assert np.median(ray[ys, xs]) - k.t[2] > 0.2


def test_nvisii_rotation_fix_reprojects_ketchup(nvisii_frame, nvisii_json, ketchup_size):
    """Rebuilt pose + K + the mesh's box in the legacy order reproduce projected_cuboid < 1 px;
    the exported quaternion does not (the objects are scaled cm -> m)."""
    size, center = ketchup_size
    size_legacy = np.abs(LEGACY_TO_MESH.T) @ size
    kp_mesh = cuboid_keypoints(size_legacy) @ LEGACY_TO_MESH.T + center  # legacy order
    raw = json.loads(nvisii_json.read_text())["objects"]
    n = 0
    for o, r in zip(nvisii_frame.objects, raw):
        if o.class_name != "Ketchup":
            continue
        n += 1
        err = np.abs(project_points(kp_mesh, nvisii_frame.K, o.R, o.t) - o.projected_cuboid).max()
        assert err < 1.0
        R_file = quaternion_xyzw_to_matrix(r["quaternion_xyzw"])
        assert rotation_error_deg(R_file, o.R) > 30.0
        # reordered into the current order it is the mesh's own current-order cuboid
        cur = legacy_keypoints_to_current(o.projected_cuboid)
        err = np.abs(project_points(cuboid_keypoints(size, center), nvisii_frame.K, o.R, o.t) - cur)
        assert err.max() < 1.0
    assert n == 14


def test_nvisii_legacy_order_detected_for_unknown_objects(nvisii_frame):
    """Objects of unknown size: the box fits the projection only in the legacy order."""
    for o in nvisii_frame.objects[:8]:
        assert o.class_name != "Ketchup"
        err_legacy = fit_cuboid_up_to_scale(o.projected_cuboid, nvisii_frame.K, o.R,
                                            ORDER_CORNER_SIGNS["dope-legacy"])[0]
        err_current = fit_cuboid_up_to_scale(o.projected_cuboid, nvisii_frame.K, o.R,
                                             ORDER_CORNER_SIGNS["dope-current"])[0]
        assert err_legacy < 0.05
        assert err_current > 10.0


def _nvisii_variant(nvisii_json: Path, tmp_path: Path, order: str, with_local: bool) -> Path:
    """The first NViSII object re-annotated with a known box in ``order``."""
    data = json.loads(nvisii_json.read_text())
    frame = read_dope_json(nvisii_json)
    o = frame.objects[0]
    half = np.array([0.05, 0.03, 0.08])
    local = np.vstack([ORDER_CORNER_SIGNS[order] * half, np.zeros(3)]) + [0.01, -0.02, 0.0]
    obj = data["objects"][0]
    obj["projected_cuboid"] = project_points(local, frame.K, o.R, o.t).tolist()
    obj["local_cuboid"] = local.tolist() if with_local else None
    data["objects"] = [obj]
    out = tmp_path / "00000.json"
    out.write_text(json.dumps(data))
    return out


@pytest.mark.parametrize("order", ["dope-current", "dope-legacy"])
@pytest.mark.parametrize("with_local", [True, False])
def test_nvisii_keypoint_order_detection(tmp_path, nvisii_json, order, with_local):
    fr = read_dope_json(_nvisii_variant(nvisii_json, tmp_path, order, with_local))
    assert fr.objects[0].keypoint_order == order


# --------------------------------------------------------------------------- project format
def _frame(rng: np.random.Generator, n: int = 2) -> FrameAnnotation:
    objs = []
    for i in range(n):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.4, 1.5)])
        K = intrinsics_matrix(600, 610, 320, 240)
        objs.append(ObjectAnnotation(
            class_name=["Ketchup", "Mustard"][i % 2], R=R, t=t,
            projected_cuboid=project_points(cuboid_keypoints([0.06, 0.15, 0.04]), K, R, t),
            visibility=float(rng.uniform()), bbox_xyxy=np.array([1.5, 2.0, 100.0, 120.25]),
            instance_id=i + 1))
    return FrameAnnotation(source=Path("x.json"), K=intrinsics_matrix(600, 610, 320, 240),
                           width=640, height=480, objects=objs)


def test_write_read_round_trip_and_file_layout(tmp_path):
    fr = _frame(np.random.default_rng(0))
    path = tmp_path / "000007.json"
    write_dope_json(path, fr, extra={"generator": {"seed": 3}})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000007.json"]  # no temp file left
    doc = json.loads(path.read_text())
    assert doc["format"] == "dope-hope" and doc["units"] == "cm"
    assert doc["keypoint_order"] == "dope-current"
    assert doc["generator"] == {"seed": 3}
    assert doc["camera_data"] == {"intrinsics": {"fx": 600.0, "fy": 610.0, "cx": 320.0, "cy": 240.0},
                                  "width": 640, "height": 480}
    o0 = doc["objects"][0]
    np.testing.assert_allclose(o0["location"], fr.objects[0].t * 100.0)  # centimetres in the file
    assert o0["bounding_box"] == {"top_left": [1.5, 2.0], "bottom_right": [100.0, 120.25]}
    assert o0["instance_id"] == 1
    assert len(o0["projected_cuboid"]) == 9
    back = read_dope_json(path)
    assert back.source == path
    np.testing.assert_allclose(back.K, fr.K)
    assert (back.width, back.height) == (640, 480)
    assert back.image_path is None
    for a, b in zip(fr.objects, back.objects):
        assert b.class_name == a.class_name
        assert rotation_error_deg(a.R, b.R) < 1e-6
        np.testing.assert_allclose(b.t, a.t, atol=1e-12)
        np.testing.assert_allclose(b.projected_cuboid, a.projected_cuboid)
        np.testing.assert_allclose(b.bbox_xyxy, a.bbox_xyxy)
        assert (b.visibility, b.instance_id, b.keypoint_order) == (a.visibility, a.instance_id,
                                                                   a.keypoint_order)
    with pytest.raises(ValueError, match="objects"):
        write_dope_json(path, fr, extra={"objects": []})


def test_round_trip_keeps_nvisii_legacy_order_and_depth_scale(tmp_path, nvisii_frame):
    path = tmp_path / "00000.json"
    write_dope_json(path, nvisii_frame)
    back = read_dope_json(path)
    assert back.depth_scale_m == 1.0
    assert all(o.keypoint_order == "dope-legacy" for o in back.objects)
    mixed = copy.deepcopy(nvisii_frame)
    mixed.objects[1].keypoint_order = "dope-current"
    write_dope_json(path, mixed)
    assert [o.keypoint_order for o in read_dope_json(path).objects[:3]] == [
        "dope-legacy", "dope-current", "dope-legacy"]


@settings(max_examples=25, deadline=None)
@given(q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
       t=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_pose_round_trip_property(tmp_path_factory, q, t):
    R = quaternion_xyzw_to_matrix(np.array(q))
    fr = FrameAnnotation(source=Path("a.json"), K=None, width=None, height=None,
                         objects=[ObjectAnnotation("Ketchup", R, np.array(t))])
    path = tmp_path_factory.mktemp("rt") / "000000.json"
    write_dope_json(path, fr)
    o = read_dope_json(path).objects[0]
    assert rotation_error_deg(R, o.R) < 1e-5
    np.testing.assert_allclose(o.t, t, atol=1e-12)
    assert o.projected_cuboid is None and o.visibility is None and o.bbox_xyxy is None


def test_list_dope_frames(tmp_path):
    for name in ("000002.json", "000002.jpg", "000001.json", "000001.png", "000003.json",
                 "000003.depth.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert list_dope_frames(tmp_path) == [tmp_path / "000001.json", tmp_path / "000002.json"]
    with pytest.raises(InputFileError, match="not found"):
        list_dope_frames(tmp_path / "nope")


def test_sibling_depth_png_and_seg(tmp_path):
    fr = _frame(np.random.default_rng(1), n=1)
    write_dope_json(tmp_path / "000000.json", fr)
    for s in (".png", ".depth.png", ".seg.png"):
        (tmp_path / f"000000{s}").write_bytes(b"")
    back = read_dope_json(tmp_path / "000000.json")
    assert back.image_path == tmp_path / "000000.png"
    assert back.depth_path == tmp_path / "000000.depth.png"
    assert back.seg_path == tmp_path / "000000.seg.png"
    assert back.depth_scale_m == 0.001


def test_read_frame_depth_png_is_scaled(tmp_path):
    fr = _frame(np.random.default_rng(2), n=0)
    fr.depth_scale_m = 0.0001
    write_dope_json(tmp_path / "000000.json", fr)
    cv2.imwrite(str(tmp_path / "000000.depth.png"), np.full((4, 5), 12345, np.uint16))
    back = read_dope_json(tmp_path / "000000.json")
    np.testing.assert_allclose(read_frame_depth_m(back), 1.2345, rtol=1e-6)
    back.depth_path = None
    with pytest.raises(InputFileError, match="no depth image"):
        read_frame_depth_m(back)


# --------------------------------------------------------------------------- errors
def _good_doc() -> dict:
    return {"format": "dope-hope", "units": "cm", "keypoint_order": "dope-current",
            "camera_data": {"intrinsics": {"fx": 500, "fy": 500, "cx": 320, "cy": 240},
                            "width": 640, "height": 480},
            "objects": [{"class": "Ketchup", "location": [1, 2, 50], "quaternion_xyzw": [0, 0, 0, 1],
                         "projected_cuboid": [[float(i), float(i)] for i in range(9)],
                         "visibility": 1.0}]}


@pytest.mark.parametrize("dotted, value, message", [
    ("objects.0.projected_cuboid", [[0.0, 0.0]] * 8,
     "objects[0].projected_cuboid: expected 9 points, got 8"),
    ("objects.0.projected_cuboid", [[0.0, 0.0, 0.0]] * 9,
     "objects[0].projected_cuboid: expected 2 coordinates per point, got 3"),
    ("objects.0.projected_cuboid", [["a", "b"]] * 9, "objects[0].projected_cuboid: expected a rectangular array of numbers"),
    ("objects.0.location", KeyError, "objects[0].location: missing field"),
    ("objects.0.location", [1, 2], "objects[0].location: expected shape (3,), got (2,)"),
    ("objects.0.quaternion_xyzw", [0, 0, 0, 0], "objects[0].quaternion_xyzw: zero quaternion"),
    ("objects.0.class", KeyError, "objects[0].class: missing field"),
    ("objects.0.visibility", 1.5, "objects[0].visibility: expected a fraction in [0, 1] or a visible pixel count"),
    ("objects.0.visibility", -2, "objects[0].visibility: expected a fraction"),
    ("camera_data.intrinsics.fx", KeyError, "camera_data.intrinsics.fx: missing field"),
    ("camera_data.intrinsics.fy", "big", "camera_data.intrinsics.fy: expected a finite number"),
    ("camera_data.width", -3, "camera_data.width: expected a positive integer"),
    ("units", "inch", "units: expected one of"),
    ("objects", {"a": 1}, "objects: expected a list"),
    ("objects.0", 7, "objects[0]: expected an object"),
])
def test_malformed_fields_name_file_and_field(tmp_path, dotted, value, message):
    path = tmp_path / "000000.json"
    path.write_text(json.dumps(with_field(_good_doc(), dotted, value)))
    with pytest.raises(InputFileError) as err:
        read_dope_json(path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_ndds_variant_errors_name_the_field(tmp_path, ndds_dir):
    data = json.loads((ndds_dir / "000000.json").read_text())
    data["objects"][0]["projected_cuboid"] = data["objects"][0]["projected_cuboid"][:8]
    path = tmp_path / "000000.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=r"objects\[0\]\.projected_cuboid: expected 9 points, got 8"):
        read_dope_json(path)


def test_nvisii_variant_errors_name_the_field(tmp_path, nvisii_json):
    data = json.loads(nvisii_json.read_text())
    data["objects"][2]["local_to_world_matrix"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    path = tmp_path / "00000.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=r"objects\[2\]\.local_to_world_matrix: expected 4 rows, got 3"):
        read_dope_json(path)


@pytest.mark.parametrize("content, message", [
    (None, "annotation file not found"),
    ("{not json", "malformed JSON (line 1"),
    ("[1, 2]", "top level: expected a JSON object"),
    (b"\xff\xfe\x00", "not a UTF-8 text file"),
])
def test_unreadable_files(tmp_path, content, message):
    path = tmp_path / "000000.json"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    with pytest.raises(DopeHopeError) as err:
        read_dope_json(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_corner_sign_tables_are_the_same_box():
    """Both orders list the 8 corners of one box, each once."""
    for signs in ORDER_CORNER_SIGNS.values():
        assert {tuple(s) for s in signs} == {tuple(s) for s in CUBOID_CORNER_SIGNS}
