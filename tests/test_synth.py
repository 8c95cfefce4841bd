"""Synthetic data generator: geometry of the annotations, determinism, resume, workers, CLI."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay, cKDTree

from dope_hope.cli import main
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.io.dope_json import list_dope_frames, read_dope_json
from dope_hope.io.images import read_depth_m, read_image_raw, read_rgb, write_rgb
from dope_hope.io.meshes import load_mesh, mesh_cuboid
from dope_hope.synth.assets import (
    guess_class_name,
    list_distractor_meshes,
)
from dope_hope.synth.background import BackgroundSource
from dope_hope.synth.camera import reference_intrinsics
from dope_hope.synth.generate import FrameGenerator, SynthJob
from dope_hope.synth.scene import frame_streams
from dope_hope.synth.settings import load_synth_config, parse_shard, parse_size
from dope_hope.synth.to_disk import generate_dataset

SIZE = (160, 120)
# Busy but small scenes: always two targets and a few distractors.
CFG = {"target": {"count": [2, 2]}, "distractors": {"count": [3, 5]}}


@pytest.fixture(scope="module")
def simple_obj(shared_data: Path) -> Path:
    return shared_data / "hope_ketchup" / "textured_simple.obj"


@pytest.fixture(scope="module")
def gen(simple_obj: Path):
    g = FrameGenerator(simple_obj, size=SIZE, config=CFG, seed=3)
    yield g
    g.close()


@pytest.fixture(scope="module")
def frames(gen):
    return [gen.render_frame(i, with_alone_depth=True) for i in range(4)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, simple_obj: Path) -> Path:
    out = tmp_path_factory.mktemp("ds") / "a"
    generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 10, progress=False)
    return out


def _target_cuboid(mesh_path: Path):
    return mesh_cuboid(load_mesh(mesh_path))


# --------------------------------------------------------------------------- annotations
def test_projected_cuboid_is_projection_of_json_pose(dataset: Path, simple_obj: Path):
    size, center = _target_cuboid(simple_obj)
    jsons = list_dope_frames(dataset)
    assert len(jsons) == 10
    n = 0
    for p in jsons:
        frame = read_dope_json(p)
        doc = json.loads(p.read_text())
        np.testing.assert_allclose(doc["cuboid"]["size_m"], size, atol=1e-9)
        np.testing.assert_allclose(doc["cuboid"]["center_m"], center, atol=1e-9)
        assert frame.width == SIZE[0] and frame.height == SIZE[1]
        kp3 = cuboid_keypoints(np.array(doc["cuboid"]["size_m"]), np.array(doc["cuboid"]["center_m"]))
        for obj in frame.objects:
            uv = project_points(kp3, frame.K, obj.R, obj.t)
            assert np.abs(uv - obj.projected_cuboid).max() < 0.01
            assert obj.class_name == "Ketchup"
            assert 0.4 - 1e-9 <= (obj.R @ center + obj.t)[2] <= 1.4 + 1e-9
            n += 1
    assert n == 20


def test_depth_on_mask_is_the_mesh_depth(frames, gen, simple_obj: Path):
    mesh = load_mesh(simple_obj)
    surface = cKDTree(trimesh.sample.sample_surface(mesh, 150_000, seed=0)[0])
    checked = 0
    for f in frames:
        K_inv = np.linalg.inv(f.annotation.K)
        for obj in f.annotation.objects:
            mask = f.seg == obj.instance_id
            if mask.sum() < 20:
                continue
            # same depth as the instance rendered alone ...
            d_scene, d_alone = f.depth_clean[mask], f.alone_depth[obj.instance_id][mask]
            assert np.median(np.abs(d_scene - d_alone)) < 1e-3
            # ... and back-projected pixels lie on the mesh under the annotated pose
            v, u = np.nonzero(mask)
            rays = np.stack([u, v, np.ones_like(u)], axis=1).astype(float) @ K_inv.T
            pts_cam = rays * f.depth_clean[mask][:, None]
            pts_model = (pts_cam - obj.t) @ obj.R  # R^T (x - t)
            dist, _ = surface.query(pts_model)
            assert np.median(dist) < 1e-3
            checked += 1
    assert checked >= 3


def test_mask_inside_projected_cuboid_hull(frames):
    checked = 0
    for f in frames:
        for obj in f.annotation.objects:
            v, u = np.nonzero(f.seg == obj.instance_id)
            if u.size == 0:
                continue
            corners = obj.projected_cuboid[:8]
            hull = Delaunay(corners)
            pts = np.stack([u, v], axis=1).astype(float)
            # pixel centres strictly inside up to numerical slack: also test 0.5 px towards the centroid
            inside = hull.find_simplex(pts) >= 0
            c = corners.mean(0)
            nudged = pts + 0.5 * (c - pts) / np.maximum(np.linalg.norm(c - pts, axis=1, keepdims=True), 1e-9)
            assert np.all(inside | (hull.find_simplex(nudged) >= 0))
            assert inside.mean() > 0.99
            checked += 1
    assert checked >= 4


def test_seg_ids_bbox_and_visibility(frames, gen):
    base = gen.cfg.output.seg_distractor_base
    for f in frames:
        ids = set(np.unique(f.seg).tolist())
        target_ids = {o.instance_id for o in f.annotation.objects}
        assert target_ids == set(range(1, len(f.annotation.objects) + 1))
        assert ids <= {0} | target_ids | set(range(base + 1, 256))
        assert np.all(f.depth_clean[f.seg == 0] == 0) and np.all(f.depth_clean[f.seg > 0] > 0)
        for obj, st in zip(f.annotation.objects, f.stats):
            assert 0.0 <= obj.visibility <= 1.0
            assert st.px_count_visib <= st.px_count_all
            mask = f.seg == obj.instance_id
            if mask.any():
                v, u = np.nonzero(mask)
                np.testing.assert_array_equal(obj.bbox_xyxy, [u.min(), v.min(), u.max(), v.max()])
            else:
                assert obj.bbox_xyxy is None and obj.visibility == 0.0


def test_forced_occluder_lowers_visibility_and_keeps_the_scene(gen):
    dropped = 0
    for i in range(3):
        plain = gen.render_frame(i)
        occl = gen.render_frame(i, force_occluder=0)
        a, b = plain.annotation.objects[0], occl.annotation.objects[0]
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(plain.annotation.K, occl.annotation.K)
        assert any(o.occluder_of == 1 for o in occl.scene.objects)
        assert b.visibility <= a.visibility
        if a.visibility > 0.3:
            assert b.visibility < a.visibility - 0.2
            dropped += 1
    assert dropped >= 1


def test_truncated_instances_have_lower_visibility(simple_obj: Path):
    cfg = {"target": {"count": [1, 1], "truncation_prob": 1.0, "truncation_offset": [0.3, 0.5]},
           "distractors": {"count": [0, 0], "occluder_prob": 0.0}}
    with FrameGenerator(simple_obj, size=SIZE, config=cfg, seed=1) as g:
        for i in range(3):
            f = g.render_frame(i)
            obj, st = f.annotation.objects[0], f.stats[0]
            assert st.truncated
            # centre outside the image: at most about half of the object is in view
            assert 0.0 <= obj.visibility < 0.75


def test_frames_without_a_target_are_negatives_the_trainer_reads(simple_obj: Path, tmp_path: Path):
    """target.count starting at 0 makes frames with background, distractors and look-alikes
    but no annotated instance; training reads them as frames whose maps are all zero."""
    from dope_hope.training.dataset import scan_frames

    cfg = {"target": {"count": [0, 0]}, "distractors": {"count": [3, 3]}, "hard_negatives": {"count": [1, 1]}}
    generate_dataset(tmp_path / "neg", SynthJob(simple_obj, seed=4, size=SIZE, config=cfg), 2, progress=False)
    for i in range(2):
        assert read_dope_json(tmp_path / "neg" / f"{i:06d}.json").objects == []
        seg = read_image_raw(tmp_path / "neg" / f"{i:06d}.seg.png")
        assert not np.isin(seg, [1, 2, 3]).any() and (seg > 0).any()  # no target id, other objects
    records, bad = scan_frames([tmp_path / "neg"], "Ketchup")
    assert not bad and [r.keypoints.shape for r in records] == [(0, 9, 2)] * 2
    with pytest.raises(ConfigError, match="target.count must start at 0 or more"):
        load_synth_config({"target": {"count": [-1, 2]}})


# --------------------------------------------------------------------------- determinism
def test_same_seed_gives_identical_files(dataset: Path, simple_obj: Path, tmp_path: Path):
    out = tmp_path / "b"
    generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 3, progress=False)
    for i in range(3):
        for suffix in (".json", ".png", ".seg.png", ".depth.png"):
            name = f"{i:06d}{suffix}"
            assert (out / name).read_bytes() == (dataset / name).read_bytes(), name
    other = tmp_path / "c"
    generate_dataset(other, SynthJob(simple_obj, seed=6, size=SIZE, config=CFG), 1, progress=False)
    assert (other / "000000.json").read_bytes() != (dataset / "000000.json").read_bytes()


def test_resume_after_interruption_matches_uninterrupted(dataset: Path, simple_obj: Path, tmp_path: Path):
    out = tmp_path / "r"
    generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 6, progress=False)
    # simulate a crash while frame 3 was written: its images exist, its JSON does not, and a
    # temporary file is left behind
    (out / "000003.json").unlink()
    (out / ".000003.abc123.tmp.json").write_text("{")
    summary = generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 10, progress=False)
    assert summary.written == 5 and summary.skipped == 5
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(p.name for p in dataset.iterdir())
    for name in names:
        assert (out / name).read_bytes() == (dataset / name).read_bytes(), name


def test_other_settings_in_same_folder_are_refused(dataset: Path, simple_obj: Path):
    with pytest.raises(ConfigError, match="seed"):
        generate_dataset(dataset, SynthJob(simple_obj, seed=6, size=SIZE, config=CFG), 10, progress=False)


def test_folder_made_before_a_setting_existed_names_that_setting(dataset: Path, simple_obj: Path,
                                                                 tmp_path: Path):
    out = tmp_path / "old"
    shutil.copytree(dataset, out)
    info_path = out / "_synth_info.json"
    info = json.loads(info_path.read_text())
    del info["config"]["background"]["clutter_prob"]  # as an earlier dope-hope wrote it
    info_path.write_text(json.dumps(info))
    with pytest.raises(ConfigError, match=r"other settings \(config\.background\.clutter_prob: absent "
                                          r"\(made before this setting existed\) -> 0\.\d+\)"):
        generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 12, progress=False)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in dataset.iterdir())


def test_two_workers_and_shards_give_the_same_frames(dataset: Path, simple_obj: Path, tmp_path: Path):
    out = tmp_path / "w"
    summary = generate_dataset(out, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 4, workers=2, progress=False)
    assert summary.written == 4
    for i in range(4):
        for suffix in (".json", ".png", ".seg.png", ".depth.png"):
            name = f"{i:06d}{suffix}"
            assert (out / name).read_bytes() == (dataset / name).read_bytes(), name
    sh = tmp_path / "s"
    generate_dataset(sh, SynthJob(simple_obj, seed=5, size=SIZE, config=CFG), 10, shard="1/4", progress=False)
    assert [p.stem for p in list_dope_frames(sh)] == ["000001", "000005", "000009"]
    assert (sh / "000005.json").read_bytes() == (dataset / "000005.json").read_bytes()


def test_frame_streams_depend_only_on_seed_and_index():
    a, b = frame_streams(1, 7), frame_streams(1, 7)
    assert all(a[k].random() == b[k].random() for k in a)
    assert frame_streams(1, 7)["targets"].random() != frame_streams(1, 8)["targets"].random()
    assert frame_streams(1, 7)["targets"].random() != frame_streams(2, 7)["targets"].random()


# --------------------------------------------------------------------------- inputs
def test_ply_in_millimetres_with_vertex_colours(tmp_path: Path):
    box = trimesh.creation.box(extents=[60.0, 100.0, 40.0])  # millimetres
    box.visual.vertex_colors = np.tile([220, 30, 30, 255], (len(box.vertices), 1))
    ply = tmp_path / "red_box.ply"
    box.export(ply)
    cfg = {"target": {"count": [1, 1]}, "distractors": {"count": [0, 0], "occluder_prob": 0.0},
           "post": {"jitter_prob": 0.0, "noise_prob": 0.0, "blur_prob": 0.0}}
    out = tmp_path / "ply"
    generate_dataset(out, SynthJob(ply, seed=0, size=SIZE, config=cfg, class_name="RedBox"), 3, progress=False)
    for p in list_dope_frames(out):
        doc = json.loads(p.read_text())
        np.testing.assert_allclose(doc["cuboid"]["size_m"], [0.06, 0.10, 0.04], atol=1e-9)
        frame = read_dope_json(p)
        obj = frame.objects[0]
        assert obj.class_name == "RedBox"
        kp = cuboid_keypoints(np.array([0.06, 0.10, 0.04]))
        assert np.abs(project_points(kp, frame.K, obj.R, obj.t) - obj.projected_cuboid).max() < 0.01
        seg = read_image_raw(frame.seg_path)
        rgb = read_rgb(frame.image_path).astype(float)
        on = rgb[seg == 1]
        assert len(on) > 20
        # the vertex colour is used: red dominates on the object
        assert np.median(on[:, 0]) > np.median(on[:, 1]) + 30
        depth = read_depth_m(frame.depth_path)
        assert np.all(depth[seg == 1] > 0.3) and np.all(depth[seg == 0] == 0)


def _write_textured_bop_ply(folder: Path) -> Path:
    """A BOP-style textured PLY (mm, texture_u/v, "comment TextureFile") with a blue texture."""
    from PIL import Image

    from dope_hope.synth.primitives import make_primitive

    box = make_primitive("box", np.array([60.0, 100.0, 40.0]), tile_m=100.0)
    tex = np.zeros((32, 32, 3), np.uint8)
    tex[..., 2] = 230
    Image.fromarray(tex).save(folder / "obj_000001.png")
    v, uv, f = box.vertices, np.asarray(box.visual.uv) % 1.0, box.faces
    head = ["ply", "format ascii 1.0", "comment TextureFile obj_000001.png", f"element vertex {len(v)}",
            "property float x", "property float y", "property float z", "property float texture_u",
            "property float texture_v", f"element face {len(f)}",
            "property list uchar int vertex_indices", "end_header"]
    body = [f"{a[0]} {a[1]} {a[2]} {b[0]} {b[1]}" for a, b in zip(v, uv)] + \
        [f"3 {a} {b} {c}" for a, b, c in f]
    path = folder / "obj_000001.ply"
    path.write_text("\n".join(head + body) + "\n")
    return path


def test_textured_bop_ply_in_millimetres(tmp_path: Path):
    ply = _write_textured_bop_ply(tmp_path)
    cfg = {"target": {"count": [1, 1]}, "distractors": {"count": [0, 0], "occluder_prob": 0.0},
           "post": {"jitter_prob": 0.0, "noise_prob": 0.0, "blur_prob": 0.0}}
    with FrameGenerator(ply, size=SIZE, config=cfg, seed=0, class_name="BlueBox") as g:
        np.testing.assert_allclose(g.target.cuboid_size, [0.06, 0.10, 0.04], atol=1e-9)
        for i in range(2):
            f = g.render_frame(i)
            on = f.rgb[f.seg == 1].astype(float)
            assert len(on) > 20
            # the texture is used: blue dominates on the object
            assert np.median(on[:, 2]) > np.median(on[:, 0]) + 30


def test_textured_target_is_not_rendered_dark(gen, frames):
    # The HOPE Ketchup texture (mostly red/white) must come through: trimesh's default OBJ
    # material (metallic 1) renders it nearly black.
    vals = np.concatenate([f.rgb[f.seg == o.instance_id] for f in frames for o in f.annotation.objects])
    assert vals.mean() > 50


def test_mesh_distractors_and_background_photos(simple_obj: Path, shared_data: Path, tmp_path: Path):
    lib = tmp_path / "lib"
    lib.mkdir()
    box = trimesh.creation.box(extents=[50.0, 80.0, 30.0])
    box.visual.vertex_colors = np.tile([30, 200, 30, 255], (len(box.vertices), 1))
    box.export(lib / "green.ply")
    cfg = {"distractors": {"count": [6, 6], "mesh_prob": 1.0, "occluder_prob": 0.0}}
    with FrameGenerator(simple_obj, size=SIZE, config=cfg, seed=0, distractors=lib,
                        backgrounds=shared_data / "backgrounds") as g:
        f = g.render_frame(0)
    sources = [o.source for o in f.scene.objects if o.role == "distractor"]
    assert sources and set(sources) == {"mesh"}
    assert (f.seg > g.cfg.output.seg_distractor_base).any()
    # copies of the target are never used as distractors
    found = list_distractor_meshes(shared_data, shared_data / "hope_ketchup" / "textured.obj", "Ketchup")
    assert not any("hope_ketchup" in str(p) for p in found)


def test_background_source_crops_photos(shared_data: Path):
    cfg = load_synth_config().background
    src = BackgroundSource(replace(cfg, procedural_prob_with_images=0.0), shared_data / "backgrounds")
    a = src.sample(np.random.default_rng(0), 96, 64)
    b = src.sample(np.random.default_rng(0), 96, 64)
    c = src.sample(np.random.default_rng(1), 96, 64)
    assert a.shape == (64, 96, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    proc = BackgroundSource(cfg).sample(np.random.default_rng(0), 96, 64)
    assert proc.shape == (64, 96, 3) and proc.std() > 1.0
    with pytest.raises(InputFileError):
        BackgroundSource(cfg, shared_data / "hope_ketchup" / "missing")


def test_background_photos_from_folders_and_files(shared_data: Path, tmp_path: Path):
    cfg = load_synth_config().background
    folder = sorted(BackgroundSource(cfg, shared_data / "backgrounds").files)
    extra = tmp_path / "garage.png"
    extra.write_bytes(folder[0].read_bytes())
    both = BackgroundSource(cfg, [shared_data / "backgrounds", extra]).files
    assert both == folder + [extra]  # folders' files in sorted order, then the file, as given
    with pytest.raises(InputFileError, match="not an image"):
        BackgroundSource(cfg, [extra, shared_data / "hope_ketchup" / "textured.obj"])


def test_reference_camera_scales_with_size():
    cam = load_synth_config().camera
    K = reference_intrinsics((640, 480), cam)
    np.testing.assert_allclose(K, [[615, 0, 319.5], [0, 615, 239.5], [0, 0, 1]])
    K2 = reference_intrinsics((400, 400), cam)
    np.testing.assert_allclose([K2[0, 0], K2[1, 1], K2[0, 2], K2[1, 2]], [512.5, 512.5, 199.5, 199.5])


def test_settings_parsing_and_validation(tmp_path: Path):
    assert parse_size("640x480") == (640, 480)
    assert parse_shard("2/5") == (2, 5) and parse_shard(None) == (0, 1)
    for bad in ("640", "axb", "0x10"):
        with pytest.raises(ConfigError):
            parse_size(bad)
    with pytest.raises(ConfigError):
        parse_shard("5/5")
    with pytest.raises(ConfigError, match="target.distance_m"):
        load_synth_config({"target": {"distance_m": [1.4, 0.4]}})
    user = tmp_path / "mine.yaml"
    user.write_text("target:\n  count: [1, 1]\n")
    cfg = load_synth_config(user)
    assert cfg.target.count == [1, 1] and cfg.lights.count == [1, 4]


def test_class_name_of_a_target_mesh_falls_back_on_the_stem(tmp_path: Path):
    assert guess_class_name(tmp_path / "bop" / "obj_000011.ply") == "Ketchup"
    assert guess_class_name(tmp_path / "meshes" / "hope_ketchup.obj") == "Ketchup"
    assert guess_class_name(tmp_path / "my_widget.obj") == "my_widget"


# --------------------------------------------------------------------------- CLI
def test_cli_writes_frames_and_preview(simple_obj: Path, tmp_path: Path, capsys):
    out = tmp_path / "cli"
    rc = main(["synth", "--mesh", str(simple_obj), "--out", str(out), "--count", "2", "--size", "160x120",
               "--preview", "--depth-noise", "--no-progress", "--set", "target.count=[1,1]"])
    assert rc == 0
    assert (out / "preview.png").is_file() and len(list_dope_frames(out)) == 2
    doc = json.loads((out / "000000.json").read_text())
    assert doc["synth"]["depth_noise"] is True and doc["synth"]["seed"] == 0
    assert "2 frames written" in capsys.readouterr().out


def test_cli_backgrounds_from_folders_and_files(simple_obj: Path, shared_data: Path, tmp_path: Path):
    photo = tmp_path / "lab.png"
    write_rgb(photo, np.full((120, 160, 3), 200, np.uint8))
    common = ["synth", "--mesh", str(simple_obj), "--count", "1", "--size", "32x32", "--no-progress"]
    assert main(common + ["--out", str(tmp_path / "one"), "--backgrounds", str(shared_data / "backgrounds")]) == 0
    assert main(common + ["--out", str(tmp_path / "two"), "--backgrounds", str(shared_data / "backgrounds"),
                          str(photo)]) == 0
    info = {name: json.loads((tmp_path / name / "_synth_info.json").read_text()) for name in ("one", "two")}
    assert info["one"]["backgrounds"] == "backgrounds"  # as a one-folder dataset always recorded it
    assert info["two"]["backgrounds"] == ["backgrounds", "lab.png"]


def test_cli_reports_bad_input_in_one_line(tmp_path: Path, capsys):
    rc = main(["synth", "--mesh", str(tmp_path / "nope.obj"), "--out", str(tmp_path / "o"), "--count", "1"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert "nope.obj" in err and len(err.splitlines()) == 1
    assert main(["synth", "--out", str(tmp_path / "o"), "--count", "1"]) == 2


def test_a_worker_error_that_cannot_be_pickled_reaches_the_parent_as_its_text():
    """An OpenGL error holds ctypes arguments, which do not pickle: the pool would report only
    "cannot pickle" (seen on a machine whose PyOpenGL failed in glGenTextures)."""
    import ctypes
    import pickle

    from dope_hope.synth.pool import _picklable

    def failing_gl_call():
        raise OSError("glGenTextures failed", ctypes.byref(ctypes.c_int()))  # as PyOpenGL's errors

    try:
        failing_gl_call()
    except OSError as error:
        with pytest.raises(TypeError):
            pickle.dumps(error)
        sent = _picklable(error, 7)
    received = pickle.loads(pickle.dumps(sent))
    assert isinstance(received, RuntimeError)
    assert str(received).startswith("frame 7: OSError: ") and "glGenTextures failed" in str(received)
    assert "failing_gl_call" in str(received)  # the worker's traceback comes along
    plain = ConfigError("bad setting")
    assert _picklable(plain, 3) is plain  # picklable errors keep their type (exit status 2)
