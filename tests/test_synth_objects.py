"""Procedural pretraining objects (dope_hope/synth/objects.py), their canonical labels and the
pretrained start's selection (``dope-hope train --init``)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.catalog import HOPE_OBJECTS
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.symmetry.transforms import category_symmetries
from dope_hope.synth.objects import SHAPE_LABELS, SHAPE_SIZES, sample_object
from dope_hope.synth.scene import MaterialSpec, ObjectSpec, SceneSpec

ALL = {"cuboid": 1.0, "cylinder": 1.0, "bottle": 1.0}


def test_objects_are_deterministic_and_of_hope_sizes():
    seen = set()
    for seed in range(24):
        a = sample_object(np.random.default_rng(seed), ALL, size_jitter=0.25, texture_px=64)
        b = sample_object(np.random.default_rng(seed), ALL, size_jitter=0.25, texture_px=64)
        assert a.category == b.category
        np.testing.assert_array_equal(a.asset.mesh.vertices, b.asset.mesh.vertices)
        np.testing.assert_array_equal(a.asset.texture, b.asset.texture)
        seen.add(a.category)
        size = a.asset.cuboid_size
        refs = np.stack([o.size_array for o in HOPE_OBJECTS if o.category == a.category])
        # every extent within the jitter of some HOPE object of the category
        assert np.all(size >= refs.min(axis=0) / 1.25 - 1e-9) and np.all(size <= refs.max(axis=0) * 1.25 + 1e-9)
        np.testing.assert_allclose(a.asset.cuboid_center, 0.0, atol=1e-9)  # centred: symmetries act about it
        uv = np.asarray(a.asset.mesh.visual.uv)
        assert uv.shape == (len(a.asset.mesh.vertices), 2) and np.all(uv[:, 1] >= 0) and np.all(uv[:, 1] <= 1)
        if a.category == "cylinder":
            assert size[0] == pytest.approx(size[2], rel=1e-3)      # round: any turn about y is a symmetry
        if a.category == "bottle":
            assert size[0] >= size[2]                               # elliptic body, wider along x
            assert size[1] > size[0]                                # standing along y
        assert not a.asset.cacheable
    assert seen == set(ALL)


@pytest.mark.parametrize("shape", sorted(SHAPE_SIZES))
def test_shapes_beyond_the_hope_categories(shape):
    """Jars, tubes, pouches, rounded boxes and irregular bodies: deterministic, centred, of
    their size ranges, labelled with their category's symmetries, and each one a new shape."""
    lows = np.array([r[0] if r else 0.0 for r in SHAPE_SIZES[shape]])
    highs = np.array([r[1] if r else np.inf for r in SHAPE_SIZES[shape]])
    outlines = set()
    for seed in range(6):
        a = sample_object(np.random.default_rng(seed), {shape: 1.0}, texture_px=32)
        b = sample_object(np.random.default_rng(seed), {shape: 1.0}, texture_px=32)
        np.testing.assert_array_equal(a.asset.mesh.vertices, b.asset.mesh.vertices)
        assert a.category == SHAPE_LABELS[shape] and a.asset.path.name == f"<procedural {shape}>"
        size = a.asset.cuboid_size
        assert np.all(size >= lows - 1e-9) and np.all(size <= highs + 1e-9)
        np.testing.assert_allclose(a.asset.cuboid_center, 0.0, atol=1e-9)
        uv = np.asarray(a.asset.mesh.visual.uv)
        assert uv.shape == (len(a.asset.mesh.vertices), 2) and np.all((uv[:, 1] >= 0) & (uv[:, 1] <= 1))
        if shape == "tube":                                         # elongated along y
            assert size[1] > size[0] >= size[2]
        outlines.add(tuple(np.round(size / size.max(), 4)))
    assert len(outlines) == 6


def test_whole_object_scale_spans_its_range_and_keeps_the_default_objects():
    sizes = [sample_object(np.random.default_rng(s), {"cuboid": 1.0}, size_jitter=0.0, texture_px=32,
                           scale=(0.5, 2.0)).asset.cuboid_size for s in range(40)]
    base = [sample_object(np.random.default_rng(s), {"cuboid": 1.0}, size_jitter=0.0,
                          texture_px=32).asset.cuboid_size for s in range(40)]
    ratio = np.array([a.max() / b.max() for a, b in zip(sizes, base)])
    assert ratio.min() >= 0.5 - 1e-9 and ratio.max() <= 2.0 + 1e-9
    assert ratio.min() < 0.7 and ratio.max() > 1.4                  # the range is used
    for a, b in zip(sizes, base):                                   # a factor on the whole object
        np.testing.assert_allclose(a / a.max(), b / b.max(), atol=1e-9)


def _scene_with(R: np.ndarray, t: np.ndarray) -> SceneSpec:
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    obj = ObjectSpec(role="target", seg_id=1, R=R, t=t, radius=0.1, center=t, source="target",
                     material=MaterialSpec(np.ones(4), 0.0, 0.5))
    return SceneSpec(width=640, height=480, K=K, znear=0.05, zfar=10.0, objects=[obj])


@pytest.mark.parametrize("category,size", [("bottle", [0.065, 0.149, 0.043]), ("cuboid", [0.1, 0.05, 0.03]),
                                           ("cylinder", [0.07, 0.06, 0.07])])
def test_symmetric_views_get_one_label(category, size):
    """Two poses that differ by a symmetry of the category look the same: the annotation gives
    them the same projected cuboid (what the network is asked to predict), and that cuboid is
    the one of a symmetric-equivalent pose."""
    from dope_hope.synth.annotate import canonical_pose_labels

    size = np.array(size)
    kp3 = cuboid_keypoints(size)
    syms = category_symmetries(category, step_deg=90.0)[:, :3, :3]
    rng = np.random.default_rng(3)
    K = _scene_with(np.eye(3), np.zeros(3)).K
    changed = 0
    for _ in range(20):
        R = Rotation.random(random_state=rng).as_matrix()
        t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.5, 1.0)])
        S = syms[int(rng.integers(1, len(syms)))]
        labels = []
        for pose in (R, R @ S):
            out = canonical_pose_labels(_scene_with(pose, t), category, size).objects[0]
            labels.append(project_points(kp3, K, out.R, out.t))
            # a symmetric equivalent of the rendered pose, same translation
            rel = pose.T @ out.R
            assert min(np.abs(rel - s).max() for s in syms) < 1e-9
            np.testing.assert_array_equal(out.t, t)
        np.testing.assert_allclose(labels[0], labels[1], atol=1e-6)
        changed += not np.allclose(project_points(kp3, K, R, t), labels[0])
    assert changed > 0  # some views are relabelled


def test_procedural_dataset_on_disk_trains_as_one_class(tmp_path):
    from dope_hope.io.dope_json import recorded_cuboid_size
    from dope_hope.synth.generate import SynthJob
    from dope_hope.synth.to_disk import generate_dataset
    from dope_hope.training.dataset import scan_frames

    cfg = {"distractors": {"count": [1, 2]}, "procedural": {"texture_px": 64}}
    for out in (tmp_path / "a", tmp_path / "b"):
        generate_dataset(out, SynthJob(None, seed=5, size=(96, 72), config=cfg, procedural=True), 3, progress=False)
    sizes = set()
    for i in range(3):
        a = json.loads((tmp_path / "a" / f"{i:06d}.json").read_text())
        b = json.loads((tmp_path / "b" / f"{i:06d}.json").read_text())
        assert a == b                                              # frame i depends on (seed, i) only
        assert {o["class"] for o in a["objects"]} <= {"Object"}
        assert a["synth"]["procedural"]["category"] in ALL
        size = recorded_cuboid_size(tmp_path / "a" / f"{i:06d}.json", "Object")
        assert size is not None
        sizes.add(tuple(np.round(size, 6)))
    assert len(sizes) == 3                                         # a new object in every frame
    records, bad = scan_frames([tmp_path / "a"], "Object")
    assert not bad and len(records) == 3
    info = json.loads((tmp_path / "a" / "_synth_info.json").read_text())
    assert info["mesh"] == "procedural" and info["cuboid_size_m"] is None


def test_procedural_config_is_checked():
    from dope_hope.synth.settings import load_synth_config

    with pytest.raises(ConfigError, match="procedural.categories"):
        load_synth_config({"procedural": {"categories": {"sphere": 1.0}}})
    with pytest.raises(ConfigError, match="procedural.size_jitter"):
        load_synth_config({"procedural": {"size_jitter": 1.5}})
    with pytest.raises(ConfigError, match="procedural.scale"):
        load_synth_config({"procedural": {"scale": [2.0, 1.0]}})
    cfg = load_synth_config({"procedural": {"categories": {"jar": 1.0, "cuboid": 0.0}}})
    assert cfg.procedural.categories.jar == 1.0


def test_the_pretraining_config_draws_every_shape_and_empty_frames():
    from dope_hope.synth.settings import load_synth_config

    cfg = load_synth_config("pretrain")
    assert set(k for k, w in cfg.procedural.categories.to_dict().items() if w > 0) == set(SHAPE_LABELS)
    assert cfg.target.count[0] == 0 and cfg.procedural.scale[1] > 1.0


def test_synth_cli_refuses_procedural_with_a_mesh(tmp_path):
    r = subprocess.run([sys.executable, "-m", "dope_hope.cli", "synth", "--procedural", "--mesh", "x.obj",
                        "--out", str(tmp_path / "o"), "--count", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--procedural" in r.stderr and r.stderr.strip().count("\n") == 0
    assert not (tmp_path / "o").exists()


def test_init_choices(tmp_path, monkeypatch):
    """auto: the shipped start only for its own architecture; pretrained: required; none: random."""
    import torch

    from dope_hope.config import load_config, merge
    from dope_hope.model import build_model
    from dope_hope.model.checkpoint import make_object_info, save_checkpoint
    from dope_hope.training import settings

    lite = load_config("lite")
    recipe = settings.TrainConfig.from_mapping
    ckpt = tmp_path / "pretrained_lite.pt"
    monkeypatch.setattr(settings, "PRETRAINED_WEIGHTS", ckpt)
    assert settings.resolve_init(None, recipe(lite))[0] is None              # not shipped: random
    with pytest.raises(InputFileError):
        settings.resolve_init("pretrained", recipe(lite))
    torch.manual_seed(0)
    save_checkpoint(ckpt, build_model(lite), lite, make_object_info("Object", [0.1, 0.1, 0.1]))
    assert settings.resolve_init(None, recipe(lite))[0] == ckpt
    assert settings.resolve_init("auto", recipe(merge(lite, {"input": {"size": [64, 64]}})))[0] == ckpt
    other = recipe(merge(lite, {"model": {"lite": {"width": 8}}}))
    path, why = settings.resolve_init(None, other)
    assert path is None and "differs" in why
    assert settings.resolve_init("none", recipe(lite)) == (None, "random start (--init none)")
    assert settings.resolve_init(str(tmp_path / "x.pt"), recipe(lite))[0] == tmp_path / "x.pt"


def test_the_shipped_pretrained_start_is_refused_as_a_detector(tmp_path):
    """Inference and export refuse the pretrained start (no object's size: wrong poses), while
    training starts from it."""
    from dope_hope.errors import ModelFileError
    from dope_hope.model.checkpoint import load_checkpoint, load_model
    from dope_hope.training.settings import PRETRAINED_WEIGHTS

    if not PRETRAINED_WEIGHTS.is_file():
        pytest.skip("this checkout has no shipped pretrained start")
    assert load_checkpoint(PRETRAINED_WEIGHTS)["config"]["model"]["arch"] == "lite"
    with pytest.raises(ModelFileError, match="pretrained start"):
        load_model(PRETRAINED_WEIGHTS)
    img = tmp_path / "x.png"
    import cv2
    cv2.imwrite(str(img), np.zeros((48, 64, 3), np.uint8))
    r = subprocess.run([sys.executable, "-m", "dope_hope.cli", "infer", str(img), "--weights", str(PRETRAINED_WEIGHTS),
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "pretrained start" in r.stderr and r.stderr.strip().count("\n") == 0
