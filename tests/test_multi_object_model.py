"""Many objects, one network: channel groups, widening, checkpoints, ONNX, predictor, CLI.

A model of N objects outputs belief (B, 9N, h, w) and affinity (B, 16N, h, w); object k owns
channels [9k, 9k + 9) and [16k, 16k + 16). The predictor is checked against
``MultiTargetsBackend``: perfect maps of known poses of several objects stacked in that
layout, so every object must come back with its own pose, class and cuboid.
"""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch
from _targets_backend import TargetsBackend
from scipy.spatial.transform import Rotation

from dope_hope import cli
from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.export.pipeline import Int8Calibration, export_checkpoint
from dope_hope.geometry import intrinsics_matrix, rotation_error_deg
from dope_hope.inference.onnx_backend import OnnxBackend
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.bop_csv import read_bop_csv
from dope_hope.model.checkpoint import load_checkpoint, load_model, make_object_info, save_checkpoint
from dope_hope.model.info import ModelInfo, ObjectInfo, group_channels
from dope_hope.model.network import build_model, widen_to_objects
from dope_hope.model.onnx_contract import output_order, parse_channel_order

torch.set_num_threads(1)

LITE = {"model": {"arch": "lite", "head": 50, "stages": 2,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}
NAMES = ("Ketchup", "Mustard", "Cookies")
#: BOP symmetry fields (mm) of a bottle turned about its own y axis by 180 degrees.
FLIP_Y = {"symmetries_discrete": [[-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]]}
K640 = intrinsics_matrix(600.0, 600.0, 319.5, 239.5)
POSES = {
    "Ketchup": [(Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix(), np.array([0.1, -0.02, 0.6]))],
    "Mustard": [(Rotation.from_euler("xyz", [-15, -60, 5], degrees=True).as_matrix(), np.array([-0.12, 0.04, 0.7])),
                (Rotation.from_euler("xyz", [5, 150, -5], degrees=True).as_matrix(), np.array([0.02, 0.08, 0.8]))],
}


def lite_config(n: int) -> dict:
    return {"model": {**LITE["model"], "num_objects": n}, "input": dict(LITE["input"])}


def objects(n: int) -> list[dict]:
    return [make_object_info(name, symmetries=FLIP_Y if name == "Mustard" else None) for name in NAMES[:n]]


class MultiTargetsBackend:
    """MapBackend of several objects: the perfect maps of one TargetsBackend per object,
    stacked in channel-group order; an object without poses gets all-zero maps."""

    def __init__(self, names, poses, K=K640, hw=(480, 640)):
        self.parts = [TargetsBackend(n, get_object(n).size_array, poses.get(n, []), K, hw) for n in names]
        first = self.parts[0]
        self.stride, self.frame, self.keypoint_order = 8, "mesh", first.keypoint_order
        self.mean, self.std, self.input_hw = first.mean, first.std, None
        objs = tuple(ObjectInfo(n, tuple(get_object(n).size_array)) for n in names)
        self.info = ModelInfo(class_name=names[0], size_m=objs[0].size_m, frame="mesh",
                              keypoint_order=first.keypoint_order, mean=first.mean, std=first.std,
                              input_hw=None, objects=objs)
        self.class_name, self.size_m = names[0], np.asarray(objs[0].size_m)

    def run(self, batch):
        maps = []
        for part in self.parts:
            if part.poses:
                maps.append(part.run(batch))
            else:
                N, _, Hp, Wp = batch.shape
                maps.append((np.zeros((N, 9, Hp // 8, Wp // 8), np.float32),
                             np.zeros((N, 16, Hp // 8, Wp // 8), np.float32)))
        return np.concatenate([b for b, _ in maps], 1), np.concatenate([a for _, a in maps], 1)


def white(hw=(480, 640)):
    return np.full((*hw, 3), 255, np.uint8)


def assert_finds(dets, poses, rot_deg=0.05, t_m=5e-4):
    """Exactly the poses of every object, each with its own class and cuboid."""
    assert sorted(d.class_name for d in dets) == sorted(n for n, ps in poses.items() for _ in ps)
    for name, ps in poses.items():
        mine = [d for d in dets if d.class_name == name]
        for d in mine:
            np.testing.assert_allclose(d.cuboid_size_m, get_object(name).size_array)
        for R, t in ps:
            errs = [(rotation_error_deg(d.R, R), np.linalg.norm(d.t - t)) for d in mine]
            assert sum(r < rot_deg and e < t_m for r, e in errs) == 1, (name, errs)


def _cli(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


# ----------------------------------------------------------------------------- network
@pytest.mark.parametrize("model", [LITE["model"], {"arch": "dope", "head": 50, "stages": 2}],
                         ids=["lite", "dope"])
def test_widened_network_repeats_the_one_object_outputs(model):
    torch.manual_seed(0)
    one = build_model(model).eval()
    with torch.no_grad():  # away from the near-zero output init: the check must see real values
        for p in one.parameters():
            p.add_(0.05 * torch.randn_like(p))
    n = 3
    many = build_model({**model, "num_objects": n}).eval()
    many.load_state_dict(widen_to_objects(one.state_dict(), model, n))
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        ref, got = one(x), many(x)
    assert len(ref) == len(got) == 2
    for (b1, a1), (bn, an) in zip(ref, got):
        assert bn.shape[1] == 9 * n and an.shape[1] == 16 * n
        scale = max(1.0, float(b1.abs().max()), float(a1.abs().max()))
        for k in range(n):
            assert float((bn[:, 9 * k:9 * k + 9] - b1).abs().max()) < 1e-5 * scale
            assert float((an[:, 16 * k:16 * k + 16] - a1).abs().max()) < 1e-5 * scale
    # A state dict of another architecture is refused, not silently reshaped.
    with pytest.raises(ConfigError, match="not a one-object"):
        widen_to_objects(many.state_dict(), model, 2)


def test_num_objects_must_be_a_whole_number():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="num_objects"):
            build_model(lite_config(1) | {"model": {**LITE["model"], "num_objects": bad}})


# ----------------------------------------------------------------------------- checkpoint
def test_checkpoint_lists_the_objects_and_old_files_load_as_one(tmp_path):
    cfg = lite_config(2)
    path = save_checkpoint(tmp_path / "two.pt", build_model(cfg), cfg, objects(2))
    ckpt = load_checkpoint(path)
    assert "object" not in ckpt and [o["class_name"] for o in ckpt["objects"]] == ["Ketchup", "Mustard"]
    info = ModelInfo.from_checkpoint(ckpt, path)
    assert info.class_names == ("Ketchup", "Mustard") and info.num_objects == 2
    assert info.objects[1].symmetries == FLIP_Y and info.objects[0].symmetries is None
    np.testing.assert_allclose(info.objects[1].size_m, get_object("Mustard").size_array)
    assert info.select("mustard").class_name == "Mustard" and info.select("Mustard").num_objects == 1
    model, _ = load_model(path)
    assert model.num_objects == 2

    with pytest.raises(ConfigError, match="num_objects"):  # 3 objects for a 2-object network
        save_checkpoint(tmp_path / "x.pt", build_model(cfg), cfg, objects(3))
    with pytest.raises(ConfigError, match="listed twice"):
        save_checkpoint(tmp_path / "x.pt", build_model(cfg), cfg,
                        [objects(1)[0], make_object_info("ketchup", [0.1] * 3)])
    assert not (tmp_path / "x.pt").exists()

    one = save_checkpoint(tmp_path / "one.pt", build_model(LITE), LITE, make_object_info("Ketchup"))
    ckpt = load_checkpoint(one)
    assert ckpt["object"] == ckpt["objects"][0]  # older readers read "object"
    del ckpt["objects"]  # a checkpoint written before the list existed
    torch.save(ckpt, tmp_path / "old.pt")
    info = ModelInfo.from_checkpoint(load_checkpoint(tmp_path / "old.pt"))
    assert info.class_names == ("Ketchup",) and info.objects[0].symmetries is None

    ckpt = load_checkpoint(path)
    ckpt["objects"] = ckpt["objects"][:1]  # the list disagrees with the network's groups
    torch.save(ckpt, tmp_path / "bad.pt")
    with pytest.raises(ModelFileError, match="lists 1 object"):
        load_checkpoint(tmp_path / "bad.pt")


# ----------------------------------------------------------------------------- ONNX
@pytest.fixture(scope="module")
def two_object_checkpoint(tmp_path_factory) -> Path:
    torch.manual_seed(1)
    cfg = lite_config(2)
    model = build_model(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return save_checkpoint(tmp_path_factory.mktemp("mo") / "two.pt", model, cfg, objects(2))


def test_onnx_holds_every_object_and_old_files_still_load(two_object_checkpoint, tmp_path):
    out = tmp_path / "two.onnx"
    res = export_checkpoint(two_object_checkpoint, out)
    b = OnnxBackend(out, threads=1)
    assert b.info.class_names == ("Ketchup", "Mustard") and b.objects[1].symmetries == FLIP_Y
    meta = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert [o["class_name"] for o in json.loads(meta["dope_hope.objects"])] == ["Ketchup", "Mustard"]
    assert res.info.num_objects == 2
    model, _ = load_model(two_object_checkpoint)
    x = np.random.default_rng(0).normal(size=(1, 3, 64, 64)).astype(np.float32)
    with torch.no_grad():
        tb, ta = model(torch.from_numpy(x))[-1]
    ob, oa = b.run(x)
    assert ob.shape == (1, 18, 8, 8) and oa.shape == (1, 32, 8, 8)
    assert np.abs(ob - tb.numpy()).max() < 1e-4 and np.abs(oa - ta.numpy()).max() < 1e-4

    # INT8: one file for the whole model, compared with fp32 group by group.
    calib = tmp_path / "calib"
    calib.mkdir()
    for i in range(2):
        cv2.imwrite(str(calib / f"{i}.png"), np.random.default_rng(i).integers(0, 255, (64, 64, 3), np.uint8))
    q = export_checkpoint(two_object_checkpoint, tmp_path / "two_int8.onnx", int8=Int8Calibration(calib, count=2))
    int8 = OnnxBackend(tmp_path / "two_int8.onnx")
    assert int8.info.precision == "int8" and int8.info.class_names == ("Ketchup", "Mustard")
    assert q.int8 is not None and q.int8.images == 2
    ib, ia = int8.run(x)
    assert ib.shape == ob.shape and ia.shape == oa.shape

    # A file without the objects key (as every file was before it) is the one object class_name.
    one = save_checkpoint(tmp_path / "one.pt", build_model(LITE), LITE, make_object_info("Ketchup"))
    export_checkpoint(one, tmp_path / "one.onnx")
    proto = onnx.load(str(tmp_path / "one.onnx"))
    keep = [(p.key, p.value) for p in proto.metadata_props if p.key != "dope_hope.objects"]
    del proto.metadata_props[:]
    for k, v in keep:
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(proto, str(tmp_path / "old.onnx"))
    old = OnnxBackend(tmp_path / "old.onnx")
    assert old.info.class_names == ("Ketchup",) and old.class_name == "Ketchup"
    np.testing.assert_allclose(old.size_m, get_object("Ketchup").size_array)


def test_isaac_ros_export_of_one_object(two_object_checkpoint, tmp_path):
    args = ["export", "--weights", two_object_checkpoint, "--layout", "isaac-ros", "--height", "64", "--width", "64"]
    rc, _, err = _cli(args + ["--out", tmp_path / "a.onnx"])
    assert rc == 2 and "--object" in err and "Ketchup, Mustard" in err and err.count("\n") == 1, err
    rc, _, err = _cli(args + ["--out", tmp_path / "a.onnx", "--object", "Soup"])
    assert rc == 2 and "--object" in err and "'Soup'" in err and "Ketchup, Mustard" in err, err
    assert not (tmp_path / "a.onnx").exists()

    rc, out, err = _cli(args + ["--out", tmp_path / "mustard.onnx", "--object", "mustard"])
    assert rc == 0, err
    assert "object_name:=Mustard" in out and '"Mustard": [' in out  # launch argument, dope_config entry
    b = OnnxBackend(tmp_path / "mustard.onnx")
    assert b.layout == "isaac-ros" and b.info.class_names == ("Mustard",) and b.objects[0].symmetries == FLIP_Y
    np.testing.assert_allclose(b.size_m, get_object("Mustard").size_array)
    # The graph's output is the Mustard group, in the Isaac ROS vertex order.
    model, _ = load_model(two_object_checkpoint)
    x = np.random.default_rng(1).normal(size=(1, 3, 64, 64)).astype(np.float32)
    with torch.no_grad():
        belief, affinity = model(torch.from_numpy(x))[-1]
    maps = torch.cat([belief, affinity], 1).numpy()[0]
    order = group_channels(1, 2)[output_order(parse_channel_order(b.info.extra["isaac_ros.channel_order"]))]
    raw = b.session.run(None, {"input": b.graph_input(x)})[0][0]
    assert raw.shape == (25, 8, 8) and np.abs(raw - maps[order]).max() < 1e-4
    got_b, got_a = b.run(x)  # the backend puts the channels back in the model's order
    assert np.abs(got_b[0] - maps[9:18]).max() < 1e-4 and np.abs(got_a[0] - maps[18 + 16:18 + 32]).max() < 1e-4


# ----------------------------------------------------------------------------- predictor
def test_predictor_returns_every_object_from_one_forward_pass(monkeypatch):
    backend = MultiTargetsBackend(NAMES, POSES)  # Cookies: absent, all-zero maps
    calls = []
    import dope_hope.inference.predictor as predictor_module

    real = predictor_module.corner_candidates

    def counting(belief, *a, **kw):
        calls.append(belief.shape)
        return real(belief, *a, **kw)

    monkeypatch.setattr(predictor_module, "corner_candidates", counting)
    searches = []
    real_peaks = predictor_module.decoder_peaks
    monkeypatch.setattr(predictor_module, "decoder_peaks", lambda b, *a: searches.append(b.shape) or real_peaks(b, *a))
    p = DopePredictor(backend, height=400)
    assert p.class_names == NAMES
    dets = p.predict(white(), K640)
    assert_finds(dets, POSES)
    assert len(calls) == 2 and all(s[0] == 9 for s in calls)  # the absent Cookies group is not decoded
    assert [s[0] for s in searches] == [18]  # one peak search over both present objects' maps
    assert sum(len(part.calls) for part in backend.parts) == 2  # one forward pass (no call for Cookies)
    assert [d.score for d in dets] == sorted((d.score for d in dets), reverse=True)
    with pytest.raises(AttributeError, match="use .objects"):
        p.class_name  # noqa: B018 - a multi-object predictor has no one class

    calls.clear()
    only = DopePredictor(backend, height=400, classes=["mustard"])
    assert only.class_names == ("Mustard",) and only.class_name == "Mustard"
    assert_finds(only.predict(white(), K640), {"Mustard": POSES["Mustard"]})
    assert len(calls) == 1
    with pytest.raises(ConfigError, match=r"classes: 'Soup' is not an object of this model \(its objects: "
                                          r"Ketchup, Mustard, Cookies\)"):
        DopePredictor(backend, classes=["Soup"])


def test_each_object_uses_its_own_mesh(tmp_path):
    import trimesh

    size = get_object("Mustard").size_array
    box = trimesh.creation.box(extents=size * 1.1)  # within 25 %: replaces the model's cuboid
    box.apply_translation([0.0, 0.01, 0.0])
    p = DopePredictor(MultiTargetsBackend(NAMES[:2], POSES), height=400, mesh={"Mustard": box})
    ketchup, mustard = p.objects
    assert ketchup.mesh is None and mustard.mesh is box
    np.testing.assert_allclose(mustard.cuboid_size_m, size * 1.1)
    np.testing.assert_allclose(ketchup.cuboid_size_m, get_object("Ketchup").size_array)
    with pytest.raises(ConfigError, match="mapping"):
        DopePredictor(MultiTargetsBackend(NAMES[:2], POSES), mesh=box)

    # classes= a subset that skips the model's first object: each reported object still gets its own mesh.
    sub = DopePredictor(MultiTargetsBackend(NAMES, POSES), height=400, classes=["Mustard", "Cookies"],
                        mesh={"Mustard": box})
    mustard_only, cookies = sub.objects
    assert mustard_only.class_name == "Mustard" and mustard_only.mesh is box and cookies.mesh is None
    np.testing.assert_allclose(mustard_only.cuboid_size_m, size * 1.1)
    np.testing.assert_allclose(cookies.cuboid_size_m, get_object("Cookies").size_array)


# ----------------------------------------------------------------------------- CLI
@pytest.fixture()
def image_dir(tmp_path) -> Path:
    d = tmp_path / "images"
    d.mkdir()
    cv2.imwrite(str(d / "frame.png"), white())
    return d


def _patch(monkeypatch, names=NAMES, poses=POSES):
    monkeypatch.setattr("dope_hope.inference.backends.open_backend",
                        lambda weights, backend="auto", device="cpu", threads=None: MultiTargetsBackend(names, poses))


def test_infer_classes_keeps_a_subset(image_dir, tmp_path, monkeypatch):
    _patch(monkeypatch)
    cam = ["--fx", 600, "--fy", 600, "--cx", 319.5, "--cy", 239.5, "--height", 400, "--no-overlay"]
    rc, out, err = _cli(["infer", image_dir / "frame.png", "--weights", "shelf.pt", "--out", tmp_path / "a", *cam])
    assert rc == 0, err
    records = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert sorted(r["class"] for r in records) == ["Ketchup", "Mustard", "Mustard"]
    rc, out, err = _cli(["infer", image_dir / "frame.png", "--weights", "shelf.pt", "--out", tmp_path / "b",
                         "--classes", "Ketchup", *cam])
    assert rc == 0, err
    assert [json.loads(line)["class"] for line in out.splitlines() if line.startswith("{")] == ["Ketchup"]
    rc, out, err = _cli(["infer", image_dir / "frame.png", "--weights", "shelf.pt", "--out", tmp_path / "c",
                         "--classes", "Ketchup", "Soup", *cam])
    assert rc == 2 and err.count("\n") == 1, err
    assert "--classes" in err and "'Soup'" in err and "Ketchup, Mustard, Cookies" in err


def test_bop_submit_with_one_multi_object_model(tmp_path, monkeypatch):
    W, H = 160, 120
    K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
    rot = Rotation.from_euler
    poses = {"Ketchup": [(rot("xyz", [20, -30, 15], degrees=True).as_matrix(), np.array([-0.04, 0.0, 0.6]))],
             "Mustard": [(rot("xyz", [-10, 40, 5], degrees=True).as_matrix(), np.array([0.05, 0.01, 0.65]))]}
    scene = tmp_path / "bop" / "hope" / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    cv2.imwrite(str(scene / "rgb" / "000000.png"), np.full((H, W, 3), 90, np.uint8))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K.ravel().tolist(), "depth_scale": 1.0}}))
    gts = [{"obj_id": get_object(n).obj_id, "cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": (1000 * t).tolist()}
           for n, [(R, t)] in poses.items()]
    (scene / "scene_gt.json").write_text(json.dumps({"0": gts}))
    targets = [{"scene_id": 1, "im_id": 0, "obj_id": get_object(n).obj_id, "inst_count": 1} for n in poses]
    (tmp_path / "bop" / "hope" / "test_targets_bop19.json").write_text(json.dumps(targets))

    monkeypatch.setattr("dope_hope.inference.backends.open_backend",
                        lambda weights, backend="auto", device="cpu", threads=None:
                        MultiTargetsBackend(NAMES, poses, K=K, hw=(H, W)))
    out = tmp_path / "dopehope-shelf_hope-test.csv"
    rc, stdout, err = _cli(["bop-submit", "--bop-root", tmp_path / "bop", "--weights", "shelf.pt", "--out", out,
                            "--no-depth", "--no-progress"])
    assert rc == 0, err
    rows = read_bop_csv(out, check_name=True)
    assert sorted(r.obj_id for r in rows) == sorted(get_object(n).obj_id for n in poses)
    for r in rows:
        name = next(n for n in poses if get_object(n).obj_id == r.obj_id)
        R, t = poses[name][0]
        assert rotation_error_deg(r.R, R) < 0.1 and np.linalg.norm(r.t - t) < 1e-3
    # evaluate reports per object on the multi-object submission: every pose is right.
    import trimesh

    (tmp_path / "bop" / "hope" / "models").mkdir()
    for name in poses:
        box = trimesh.creation.box(extents=get_object(name).size_array * 1000.0)  # mm
        box.export(tmp_path / "bop" / "hope" / "models" / f"obj_{get_object(name).obj_id:06d}.ply")
    rc, _, err = _cli(["evaluate", "-p", out, "-d", tmp_path / "bop" / "hope", "--format", "bop",
                       "--models-dir", tmp_path / "bop" / "hope" / "models", "--out", tmp_path / "eval",
                       "--no-progress"])
    assert rc == 0, err
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    (method,) = summary["methods"].values()
    recalls = {k: v for k, v in method["overall"].items() if k.startswith("recall")}
    assert recalls and all(v == pytest.approx(1.0) for v in recalls.values()), recalls
    table = Path(method["table_csv"]).read_text()
    assert all(f"obj_{get_object(n).obj_id:06d}" in table or n in table for n in poses), table
    # The same object in two models is refused.
    rc, _, err = _cli(["bop-submit", "--bop-root", tmp_path / "bop", "--weights", "a.pt", "b.pt",
                       "--out", tmp_path / "x_hope-test.csv", "--no-depth"])
    assert rc == 2 and "a second model for obj_id" in err
