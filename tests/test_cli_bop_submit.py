"""`dope-hope bop-submit` on a tiny BOP folder: targets, depth scale, -LS, CSV, errors.

The network is replaced by ``TargetsBackend`` (perfect maps of the ground-truth pose), so the
written poses must equal the BOP ground truth: in the CSV's units (mm), for the targeted
images only, refined with depth given in BOP's ``depth_scale`` units.
"""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from _targets_backend import TargetsBackend
from scipy.spatial.transform import Rotation

# imported before any test patches backends.open_backend: the predictor binds the name at import
import dope_hope.inference.predictor  # noqa: F401
from dope_hope import cli
from dope_hope.catalog import get_object
from dope_hope.geometry import rotation_error_deg
from dope_hope.io.bop_csv import read_bop_csv

torch.set_num_threads(1)
W, H = 160, 120
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
KETCHUP = get_object("Ketchup")
R_GT = Rotation.from_euler("xyz", [20, -30, 15], degrees=True).as_matrix()
T_GT = np.array([0.02, -0.01, 0.55])
DEPTH_SCALE_MM = 0.1  # BOP depth_scale: mm per depth unit (HOPE's BOP depth uses 0.1 too)


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def bop_root(tmp_path_factory) -> Path:
    """bop/hope/{test/000001 (2 images), test/000002 (1 image), models, test_targets_bop19.json}."""
    from dope_hope.render.depth import DepthRenderer

    root = tmp_path_factory.mktemp("bop") / "bop"
    box = trimesh.creation.box(extents=KETCHUP.size_array)
    renderer = DepthRenderer()
    depth_m = renderer.render_depth((box.vertices, box.faces), R_GT, T_GT, K, W, H)
    renderer.close()
    assert np.count_nonzero(depth_m) > 500
    for scene_id, n_images in ((1, 2), (2, 1)):
        scene = root / "hope" / "test" / f"{scene_id:06d}"
        (scene / "rgb").mkdir(parents=True)
        (scene / "depth").mkdir()
        cams, gts = {}, {}
        for im_id in range(n_images):
            cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"), np.full((H, W, 3), 90, np.uint8))
            units = np.round(depth_m * 1000.0 / DEPTH_SCALE_MM).astype(np.uint16)
            cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"), units)
            cams[str(im_id)] = {"cam_K": K.ravel().tolist(), "depth_scale": DEPTH_SCALE_MM}
            gts[str(im_id)] = [{"obj_id": KETCHUP.obj_id, "cam_R_m2c": R_GT.ravel().tolist(),
                                "cam_t_m2c": (1000.0 * T_GT).tolist()}]
        (scene / "scene_camera.json").write_text(json.dumps(cams))
        (scene / "scene_gt.json").write_text(json.dumps(gts))
    (root / "hope" / "models").mkdir()
    mm = box.copy()
    mm.apply_scale(1000.0)
    mm.export(root / "hope" / "models" / f"obj_{KETCHUP.obj_id:06d}.ply")
    targets = [{"scene_id": 1, "im_id": 0, "obj_id": KETCHUP.obj_id, "inst_count": 1},
               {"scene_id": 1, "im_id": 1, "obj_id": KETCHUP.obj_id, "inst_count": 1},
               {"scene_id": 1, "im_id": 1, "obj_id": 5, "inst_count": 1}]  # no model for obj 5
    (root / "hope" / "test_targets_bop19.json").write_text(json.dumps(targets))
    return root


def _patch_backend(monkeypatch, distance_factor: float = 1.0) -> list[TargetsBackend]:
    made = []

    def fake_open_backend(weights, backend="auto", device="cpu", threads=None):
        b = TargetsBackend("Ketchup", KETCHUP.size_array, [(R_GT, T_GT * distance_factor)], K, (H, W))
        made.append(b)
        return b

    monkeypatch.setattr("dope_hope.inference.backends.open_backend", fake_open_backend)
    return made


def test_targets_only_gt_poses_in_millimetres(bop_root, tmp_path, monkeypatch):
    made = _patch_backend(monkeypatch)
    out = tmp_path / "dopehope-test_hope-test.csv"
    rc, stdout, stderr = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", out,
                               "--no-depth", "--no-progress"])
    assert rc == 0, stderr
    rows = read_bop_csv(out, check_name=True)
    assert [(r.scene_id, r.im_id, r.obj_id) for r in rows] == [(1, 0, 11), (1, 1, 11)]  # scene 2: no target
    for r in rows:
        assert rotation_error_deg(r.R, R_GT) < 0.1
        assert np.linalg.norm(r.t - T_GT) < 1e-3 and 0 < r.score <= 1 and r.time >= 0
    assert "1,0,11," in out.read_text() and f"{1000 * T_GT[2]:.0f}" in out.read_text()  # mm on disk
    assert len(made[0].calls) == 2 * 3  # two images, three working sizes each (the accurate preset)
    assert "no model for targeted obj_id(s) 5" in stdout


def test_depth_line_search_uses_the_bop_depth_scale(bop_root, tmp_path, monkeypatch):
    _patch_backend(monkeypatch, distance_factor=1.1)  # the "network" is 10 % too far
    plain, refined = tmp_path / "a_hope-test.csv", tmp_path / "b_hope-test.csv"
    assert _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", plain,
                 "--no-depth", "--no-progress"])[0] == 0
    rc, _, stderr = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", refined,
                          "--no-progress"])
    assert rc == 0, stderr
    for p, r in zip(read_bop_csv(plain), read_bop_csv(refined)):
        assert np.linalg.norm(p.t - T_GT) > 0.04          # 10 % of 55 cm off
        assert np.linalg.norm(r.t - T_GT) < 0.004         # pulled back onto the depth image


def test_icp_corrects_the_rotation_on_the_bop_depth(bop_root, tmp_path, monkeypatch):
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("y", 20, degrees=True).as_matrix()  # the "network" turns the box

    def fake_open_backend(weights, backend="auto", device="cpu", threads=None):
        return TargetsBackend("Ketchup", KETCHUP.size_array, [(R_GT @ turn, T_GT * 1.05)], K, (H, W))

    monkeypatch.setattr("dope_hope.inference.backends.open_backend", fake_open_backend)
    ls, icp = tmp_path / "a_hope-test.csv", tmp_path / "b_hope-test.csv"
    assert _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", ls, "--no-progress",
                 "--fast"])[0] == 0  # -LS alone
    rc, _, stderr = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", icp,
                          "--icp", "--no-progress", "--fast"])
    assert rc == 0, stderr
    for a, b in zip(read_bop_csv(ls), read_bop_csv(icp)):
        assert rotation_error_deg(a.R, R_GT) > 15
        assert rotation_error_deg(b.R, R_GT) < 1.5 and np.linalg.norm(b.t - T_GT) < 0.004
    default = tmp_path / "d_hope-test.csv"  # the accurate preset: ICP where there is depth and a mesh
    assert _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", default, "--no-progress"])[0] == 0
    for a, b in zip(read_bop_csv(icp), read_bop_csv(default)):
        assert rotation_error_deg(b.R, R_GT) < 1.5 and np.linalg.norm(b.t - a.t) < 0.002
    rc, _, stderr = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out",
                          tmp_path / "c_hope-test.csv", "--icp", "--no-depth"])
    assert rc == 2 and "--icp" in stderr and "--no-depth" in stderr


def test_bad_names_existing_files_and_missing_split_fail_with_one_line(bop_root, tmp_path, monkeypatch):
    _patch_backend(monkeypatch)
    rc, _, err = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt",
                       "--out", tmp_path / "my_method_hope-test.csv"])
    assert rc == 2 and "no underscore" in err and len(err.strip().splitlines()) == 1
    existing = tmp_path / "m_hope-test.csv"
    existing.write_text("x")
    rc, _, err = _run(["bop-submit", "--bop-root", bop_root, "--weights", "k.pt", "--out", existing])
    assert rc == 2 and "--overwrite" in err and existing.read_text() == "x"
    rc, _, err = _run(["bop-submit", "--bop-root", tmp_path, "--weights", "k.pt",
                       "--out", tmp_path / "n_hope-test.csv"])
    assert rc == 2 and "BOP split folder not found" in err


def test_real_checkpoint_runs_end_to_end(bop_root, tmp_path):
    """A tiny random lite Ketchup checkpoint through the real torch backend: a valid CSV
    (possibly empty: an untrained network finds nothing) that `dope-hope evaluate` reads."""
    from dope_hope.model import build_model
    from dope_hope.model.checkpoint import make_object_info, save_checkpoint

    cfg = {"model": {"arch": "lite", "head": 50, "stages": 1,
                     "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
           "input": {"size": [64, 64]}}
    ckpt = save_checkpoint(tmp_path / "ketchup.pt", build_model(cfg), cfg, make_object_info("Ketchup"))
    out = tmp_path / "dopehope-lite_hope-test.csv"
    rc, stdout, stderr = _run(["bop-submit", "--bop-root", bop_root, "--dataset", "hope", "--split", "test",
                               "--weights", ckpt, "--out", out, "--no-progress"])
    assert rc == 0, stderr
    assert out.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert "for 2 image(s)" in stdout
    rc, _, stderr = _run(["evaluate", "-p", out, "-d", bop_root / "hope", "--format", "bop",
                          "--models-dir", bop_root / "hope" / "models", "--out", tmp_path / "eval",
                          "--no-progress"])
    assert rc == 0, stderr
    assert (tmp_path / "eval" / "summary.json").is_file()
