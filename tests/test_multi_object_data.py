"""Several objects in the data path: synth of several targets, class names of meshes, BOP-format
training data (alone and mixed with DOPE folders), training targets and checkpoints of N objects."""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from dope_hope.cli import main
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.io.dope_json import list_dope_frames, read_dope_json
from dope_hope.io.images import read_image_raw, write_rgb
from dope_hope.io.meshes import load_mesh, mesh_cuboid
from dope_hope.io.models_dir import mesh_class_name
from dope_hope.synth.generate import FrameGenerator, load_targets
from dope_hope.synth.writer import write_frame

torch.set_num_threads(1)
SIZE = (96, 72)
#: two or three targets per frame, near the camera (the grocery objects are small), few distractors
CFG = {"target": {"count": [2, 3], "distance_m": [0.25, 0.4]}, "distractors": {"count": [1, 2]}}
TINY = {"input": {"size": [64, 64]},
        "train": {"batch_size": 2, "workers": 0, "time_limit_min": None, "log_every": 1, "threads": 1,
                  "plots": False, "val_fraction": 0.2}}


@pytest.fixture(scope="module")
def grocery(shared_data: Path) -> dict[str, Path]:
    return {n: shared_data / "grocery_objects" / n / "textured.obj" for n in ("Can", "Lemon")}


def _boxes(grocery: dict[str, Path]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {n: mesh_cuboid(load_mesh(p, units="m")) for n, p in grocery.items()}


# ----------------------------------------------------------------------------- synth
@pytest.fixture(scope="module")
def two_object_frames(tmp_path_factory, grocery) -> Path:
    out = tmp_path_factory.mktemp("two") / "frames"
    code = main(["synth", "--mesh", str(grocery["Can"]), str(grocery["Lemon"]), "--units", "m",
                 "--out", str(out), "--count", "4", "--size", f"{SIZE[0]}x{SIZE[1]}", "--seed", "3",
                 "--no-progress", "--set", "target.count=[2,3]", "target.distance_m=[0.25,0.4]",
                 "distractors.count=[1,2]"])
    assert code == 0
    return out


def test_synth_writes_both_classes_with_their_own_projected_cuboids(two_object_frames, grocery):
    boxes = _boxes(grocery)
    seen = set()
    for path in list_dope_frames(two_object_frames):
        frame = read_dope_json(path)
        doc = json.loads(path.read_text())
        assert [c["class"] for c in doc["cuboid"]] == ["Can", "Lemon"]
        for obj in frame.objects:
            seen.add(obj.class_name)
            size, center = boxes[obj.class_name]
            expected = project_points(cuboid_keypoints(size, center), frame.K, obj.R, obj.t)
            np.testing.assert_allclose(obj.projected_cuboid, expected, atol=1e-3)
        seg = read_image_raw(path.with_suffix(".seg.png"))
        seg = seg[..., 0] if seg.ndim == 3 else seg
        # instance ids of the JSON are the seg ids; a visible instance has pixels there
        for obj in frame.objects:
            assert (obj.visibility > 0) == bool((seg == obj.instance_id).any())
    assert seen == {"Can", "Lemon"}
    info = json.loads((two_object_frames / "_synth_info.json").read_text())
    assert info["class"] == ["Can", "Lemon"] and info["units"] == "m"
    np.testing.assert_allclose(info["cuboid_size_m"][0], boxes["Can"][0], atol=1e-9)


def test_targets_occlude_each_other_and_frames_draw_which_appear(grocery):
    with FrameGenerator([grocery["Can"], grocery["Lemon"]], size=SIZE, units="m", seed=1,
                        config={"target": {"count": [0, 3], "distance_m": [0.25, 0.4]},
                                "distractors": {"count": [0, 0]}, "hard_negatives": {"count": [0, 0]}}) as gen:
        shown = [sorted({o.target_index for o in gen.sample_scene(i)[0].targets}) for i in range(40)]
        frame = gen.render_frame(0)
    assert [] in shown and [0] in shown and [1] in shown and [0, 1] in shown
    assert {o.class_name for o in frame.annotation.objects} <= {"Can", "Lemon"}
    # the generator's frames of one target object are the one-object generator's
    with FrameGenerator([grocery["Can"]], size=SIZE, units="m", seed=1, config=CFG) as a, \
            FrameGenerator(grocery["Can"], size=SIZE, units="m", seed=1, config=CFG) as b:
        sa, sb = a.sample_scene(2)[0], b.sample_scene(2)[0]
    assert [o.t.tolist() for o in sa.objects] == [o.t.tolist() for o in sb.objects]


def test_models_dir_with_several_objects(tmp_path, shared_data, grocery):
    out = tmp_path / "md"
    assert main(["synth", "--models-dir", str(shared_data / "grocery_objects"), "--object", "Lemon", "Can",
                 "--units", "m", "--out", str(out), "--count", "2", "--size", "64x48", "--no-progress",
                 "--set", "target.count=[2,2]", "distractors.count=[0,1]"]) == 0
    info = json.loads((out / "_synth_info.json").read_text())
    assert info["class"] == ["Lemon", "Can"]
    classes = {o.class_name for p in list_dope_frames(out) for o in read_dope_json(p).objects}
    assert classes <= {"Lemon", "Can"} and classes


def test_object_all_with_a_models_dir_is_every_object_it_holds(tmp_path, shared_data, capsys):
    from dope_hope.io.models_dir import objects_in_folder

    grocery = shared_data / "grocery_objects"
    assert objects_in_folder(grocery) == ["Bread", "Can", "Cereal", "Lemon", "Milk"]
    bop = tmp_path / "models"
    bop.mkdir()
    for name in ("obj_000011.ply", "widget.obj"):
        (bop / name).write_text("")
    (bop / "models_info.json").write_text("{}")
    assert objects_in_folder(bop) == ["Ketchup", "widget"]  # obj_000011: the HOPE catalog's Ketchup
    out = tmp_path / "all"
    assert main(["synth", "--models-dir", str(grocery), "--object", "all", "--units", "m", "--out", str(out),
                 "--count", "1", "--size", "64x48", "--no-progress", "--set", "distractors.count=[0,0]"]) == 0
    assert json.loads((out / "_synth_info.json").read_text())["class"] == ["Bread", "Can", "Cereal", "Lemon", "Milk"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["synth", "--models-dir", str(empty), "--object", "all", "--out", str(tmp_path / "x"),
                 "--count", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(empty) in err[0] and "no mesh" in err[0]
    assert not (tmp_path / "x").exists()


def test_class_name_rule_and_errors(tmp_path, grocery, capsys):
    assert mesh_class_name(grocery["Can"]) == "Can"                       # generic stem: folder
    assert mesh_class_name(tmp_path / "my_widget.obj") == "my_widget"     # else the stem
    assert mesh_class_name(tmp_path / "Ketchup" / "textured.obj") == "Ketchup"
    assert mesh_class_name(tmp_path / "models" / "obj_000011.ply") == "Ketchup"
    names = [t.name for t in load_targets([grocery["Can"], grocery["Lemon"]], ["A", "B"], "m")]
    assert names == ["A", "B"]
    with pytest.raises(ConfigError, match="also the class"):
        load_targets([grocery["Can"], grocery["Can"]], units="m")
    code = main(["synth", "--mesh", str(grocery["Can"]), str(grocery["Lemon"]), "--class-name", "A",
                 "--out", str(tmp_path / "x"), "--count", "1", "--no-progress"])
    assert code == 2 and "--class-name" in capsys.readouterr().err
    assert not (tmp_path / "x" / "_synth_info.json").exists()


# ----------------------------------------------------------------------------- BOP datasets
def _write_bop(root: Path, frame, masks: dict[int, tuple[np.ndarray, np.ndarray]], rgb: np.ndarray,
               obj_ids: dict[str, int], boxes) -> Path:
    """One scene of one image in BOP layout (root/models/models_info.json, root/train_pbr/000000)."""
    scene = root / "train_pbr" / "000000"
    for sub in ("rgb", "mask", "mask_visib"):
        (scene / sub).mkdir(parents=True, exist_ok=True)
    write_rgb(scene / "rgb" / "000000.png", rgb)
    gts = []
    for gt_id, obj in enumerate(frame.objects):
        gts.append({"obj_id": obj_ids[obj.class_name], "cam_R_m2c": obj.R.reshape(-1).tolist(),
                    "cam_t_m2c": (obj.t * 1000.0).tolist()})
        full, visib = masks[obj.instance_id]
        write_rgb(scene / "mask" / f"000000_{gt_id:06d}.png", np.repeat(full[..., None] * 255, 3, 2).astype(np.uint8))
        write_rgb(scene / "mask_visib" / f"000000_{gt_id:06d}.png",
                  np.repeat(visib[..., None] * 255, 3, 2).astype(np.uint8))
    (scene / "scene_gt.json").write_text(json.dumps({"0": gts}))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": frame.K.reshape(-1).tolist(),
                                                                "depth_scale": 1.0}}))
    info = {}
    for name, obj_id in obj_ids.items():
        size, center = boxes[name]
        lo = (center - size / 2) * 1000.0
        info[str(obj_id)] = {"diameter": float(np.linalg.norm(size) * 1000), **{f"min_{a}": float(v) for a, v in zip("xyz", lo)},
                             **{f"size_{a}": float(v) for a, v in zip("xyz", size * 1000.0)}}
        if name == "Can":  # the can's axis of revolution (its z, the 8 cm extent)
            info[str(obj_id)]["symmetries_continuous"] = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    (root / "models").mkdir(parents=True, exist_ok=True)
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    return root / "train_pbr"


@pytest.fixture(scope="module")
def bop_and_dope(tmp_path_factory, grocery):
    """A rendered frame of Can + Lemon written both as DOPE JSON and as a BOP dataset."""
    root = tmp_path_factory.mktemp("bop")
    cfg = {"target": {"count": [3, 3], "distance_m": [0.25, 0.35]}, "distractors": {"count": [0, 0]},
           "hard_negatives": {"count": [0, 0]}}
    with FrameGenerator([grocery["Can"], grocery["Lemon"]], size=SIZE, units="m", seed=5, config=cfg) as gen:
        synth = gen.render_frame(0, with_alone_depth=True)
        dope = root / "dope"
        dope.mkdir()
        write_frame(dope, 0, synth.rgb, synth.depth, synth.seg, synth.annotation, extra=gen.json_extra(synth))
    masks = {o.instance_id: ((synth.alone_depth[o.instance_id] > 0).astype(np.uint8),
                             (synth.seg == o.instance_id).astype(np.uint8)) for o in synth.annotation.objects}
    split = _write_bop(root / "bopds", synth.annotation, masks, synth.rgb, {"Can": 1, "Lemon": 2}, _boxes(grocery))
    return split, dope, synth


def test_bop_reader_projects_the_cuboids_the_dope_path_gives(bop_and_dope):
    from dope_hope.training.sources import scan_training_data

    split, dope, synth = bop_and_dope
    names = ["obj_000001", "obj_000002"]
    (bop_rec,), _ = scan_training_data([split], names)
    dope_rec, = [r for r in scan_training_data([dope], ["Can", "Lemon"])[0]]
    assert bop_rec.image_path.name == "000000.png" and bop_rec.json_path.name == "scene_gt.json"
    np.testing.assert_allclose(bop_rec.keypoints, dope_rec.keypoints, atol=1e-3)
    np.testing.assert_array_equal(bop_rec.classes, dope_rec.classes)
    # mixed with DOPE folders: both read, each by its format; scene folder alone works too
    mixed, _ = scan_training_data([dope, split / "000000"], names + ["Can"])
    assert len(mixed) == 2 and mixed[1].json_path.parent.name == "000000"


def test_bop_visibility_comes_from_mask_visib(bop_and_dope):
    from dope_hope.io.bop_scenes import iter_bop_frames
    from dope_hope.training.sources import scan_training_data

    split, _, synth = bop_and_dope
    frame, = iter_bop_frames(split)
    for obj, gt in zip(frame.objects, synth.annotation.objects):
        visib = (synth.seg == gt.instance_id).sum()
        full = (synth.alone_depth[gt.instance_id] > 0).sum()
        assert obj.class_name in ("obj_000001", "obj_000002")
        assert obj.visibility == pytest.approx(min(1.0, visib / full) if full else 0.0)
    strict = max(o.visibility for o in frame.objects) + 1e-6
    (rec,), _ = scan_training_data([split], ["obj_000001", "obj_000002"], min_visibility=strict)
    assert len(rec.keypoints) == 0  # every instance below the threshold


def test_bop_dataset_without_models_info_is_one_line(tmp_path, bop_and_dope, capsys):
    split, _, _ = bop_and_dope
    copy = tmp_path / "ds" / "train_pbr"
    shutil.copytree(split, copy)
    code = main(["train", "--data", str(copy), "--object", "obj_000001", "--out", str(tmp_path / "run"),
                 "--init", "none", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "models_info.json" in err[0]


# ----------------------------------------------------------------------------- training
def _dope_frames(folder: Path, grocery, n: int = 6) -> None:
    """Tiny frames: Can and Lemon in each, except frame 0 (Can only)."""
    from scipy.spatial.transform import Rotation

    from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
    from dope_hope.geometry import intrinsics_matrix
    from dope_hope.io.dope_json import write_dope_json

    boxes = _boxes(grocery)
    rng = np.random.default_rng(0)
    W, H = 80, 64
    K = intrinsics_matrix(1.2 * W, 1.2 * W, (W - 1) / 2, (H - 1) / 2)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        objects = []
        for name, x in (("Can", -0.04), ("Lemon", 0.04))[: 1 if i == 0 else 2]:
            R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            t = np.array([x, 0.0, 0.3])
            kp = project_points(cuboid_keypoints(*boxes[name]), K, R, t)
            objects.append(ObjectAnnotation(name, R, t, kp, 1.0))
        write_rgb(folder / f"{i:06d}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        write_dope_json(folder / f"{i:06d}.json", FrameAnnotation(folder / f"{i:06d}.json", K, W, H, objects))


def test_two_object_training_writes_the_object_list_and_grouped_targets(tmp_path, grocery):
    from dope_hope.config import load_config
    from dope_hope.model.checkpoint import load_checkpoint
    from dope_hope.training.settings import TrainJob
    from dope_hope.training.trainer import Trainer

    data = tmp_path / "frames"
    _dope_frames(data, grocery)
    job = TrainJob(data=[data], object_name="Can", out=tmp_path / "run", objects=["Can", "Lemon"],
                   meshes=dict(grocery), units={"Can": "m", "Lemon": "m"}, device="cpu", progress=False,
                   overrides={**TINY, "train": {**TINY["train"], "steps": 2, "plots": True}})
    trainer = Trainer(job, load_config("lite"))
    one_class = [i for i, r in enumerate(trainer.train_set.records) if len(r.keypoints) == 1]
    two_class = [i for i, r in enumerate(trainer.train_set.records) if len(r.keypoints) == 2]
    assert one_class and two_class
    item = trainer.train_set[(0, one_class[0])]
    assert item["belief"].shape[0] == 18 and item["affinity"].shape[0] == 32
    assert item["belief"][:9].max() > 0.5 and item["belief"][9:].abs().max() == 0
    assert item["affinity"][16:].abs().max() == 0
    assert item["classes"][:2].tolist() == [0, -1]
    both = trainer.train_set[(0, two_class[0])]
    assert both["belief"][9:].max() > 0.5
    summary = trainer.run()
    assert summary["status"] == "completed" and summary["objects"] == ["Can", "Lemon"]
    assert {"val_kp_acc/Can", "val_kp_acc_decoded/Lemon"} <= set(summary)
    assert (tmp_path / "run" / "val_snapshot.png").is_file()  # each object's group decoded on its own
    ck = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ck["config"]["model"]["num_objects"] == 2
    assert [o["class_name"] for o in ck["objects"]] == ["Can", "Lemon"] and "object" not in ck
    np.testing.assert_allclose(ck["objects"][1]["size_m"], _boxes(grocery)["Lemon"][0], atol=1e-9)
    out = trainer.model(torch.zeros(1, 3, 64, 64))[-1]
    assert out[0].shape[1] == 18 and out[1].shape[1] == 32
    # --resume alone continues with the checkpoint's objects, meshes and units
    again = TrainJob(data=[], object_name="", out=tmp_path / "run", resume=tmp_path / "run" / "last.pt",
                     device="cpu", progress=False, overrides={"train": {"steps": 3}})
    resumed = Trainer(again, {})
    assert again.class_names == ["Can", "Lemon"] and again.units == {"Can": "m", "Lemon": "m"}
    assert resumed.object == ck["objects"] and resumed.run()["step"] == 3


def test_train_command_pairs_meshes_with_objects_and_reads_bop(tmp_path, grocery, bop_and_dope, capsys, caplog):
    split, dope, _ = bop_and_dope
    caplog.set_level(logging.INFO, logger="dope_hope")
    run = tmp_path / "run"
    code = main(["train", "--data", str(dope), str(split), "--object", "obj_000001", "Lemon",
                 "--mesh", str(grocery["Can"]), str(grocery["Lemon"]), "--units", "m", "--out", str(run),
                 "--init", "none", "--steps", "1", "--batch-size", "1", "--workers", "0", "--no-progress",
                 "--set", "input.size=[64,64]", "train.plots=false", "train.val_fraction=0.4"])
    assert code == 0, capsys.readouterr().err
    assert any(r.getMessage().startswith("symmetries: Lemon: detected on the mesh: continuous about x")
               for r in caplog.records)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["objects"] == ["obj_000001", "Lemon"] and summary["train_frames"] + summary["val_frames"] == 2
    from dope_hope.model.checkpoint import load_checkpoint

    objects = load_checkpoint(run / "last.pt")["objects"]  # symmetries from the BOP models_info.json
    assert objects[0]["symmetries"] == {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    # the lemon declares none: those found on its mesh (mm), continuous about its long axis x
    lemon = objects[1]["symmetries"]
    assert len(lemon["symmetries_continuous"]) == 1 and len(lemon["symmetries_discrete"]) == 1
    np.testing.assert_allclose(lemon["symmetries_continuous"][0]["axis"], [1, 0, 0], atol=1e-9)


def test_a_one_object_start_is_widened_to_the_run_objects():
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.config import load_config
    from dope_hope.model.network import build_model
    from dope_hope.training.init_weights import load_init_weights
    from dope_hope.training.objects import with_num_objects
    from dope_hope.training.settings import TrainConfig

    if not PRETRAINED_WEIGHTS.is_file():
        pytest.skip("this installation ships no pretrained start")
    model = build_model(with_num_objects(TrainConfig.from_mapping(load_config("lite")), 3).to_dict()).eval()
    load_init_weights(model, PRETRAINED_WEIGHTS)
    with torch.no_grad():
        belief, affinity = model(torch.rand(1, 3, 64, 64))[-1]
    torch.testing.assert_close(belief[:, 18:27], belief[:, :9], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(affinity[:, 16:32], affinity[:, :16], atol=1e-5, rtol=1e-4)


def test_train_meshes_pair_in_order_by_name_or_from_a_models_dir(shared_data, grocery, tmp_path):
    from dope_hope.training.settings import train_meshes

    can, lemon = str(grocery["Can"]), str(grocery["Lemon"])
    assert train_meshes(["Can", "Lemon"], [can, lemon], None, ["m"]) == (
        {"Can": Path(can), "Lemon": Path(lemon)}, {"Can": "m", "Lemon": "m"})
    assert train_meshes(["Can", "Lemon"], [f"Lemon={lemon}"], None)[0] == {"Lemon": Path(lemon)}
    models = train_meshes(["Lemon", "Can"], None, shared_data / "grocery_objects", ["m", "cm"])
    assert models == ({"Lemon": Path(lemon), "Can": Path(can)}, {"Lemon": "m", "Can": "cm"})
    with pytest.raises(ConfigError, match="Milk is not an object of this run"):
        train_meshes(["Can", "Lemon"], [f"Milk={lemon}"], None)
    with pytest.raises(ConfigError, match="Milk is not an object of this run"):
        train_meshes(["Can"], [f"Milk={lemon}"], None)  # one object, one mesh: still named
    with pytest.raises(ConfigError, match="either --mesh or --models-dir"):
        train_meshes(["Can"], [can], shared_data / "grocery_objects")
    with pytest.raises(ConfigError, match="--units"):
        train_meshes(["Can", "Lemon"], [can, lemon], None, ["m", "m", "m"])


def test_evaluate_takes_a_unit_per_object_mesh(shared_data, grocery):
    from dope_hope.commands.argtypes import parse_mesh_units as mesh_units
    from dope_hope.evaluation.object_models import load_models

    assert mesh_units([]) is None and mesh_units(["mm"]) == "mm"
    assert mesh_units(["cm", "can=m"]) == {"": "cm", "can": "m"}
    assert mesh_units(["ketchup=cm"]) == {"Ketchup": "cm"}  # catalog names in their spelling
    assert mesh_units(["all=m"]) == "m"
    for bad in (["km"], ["Can=m", "Can=cm"], ["m", "cm"]):
        with pytest.raises(ConfigError, match="--mesh-units"):
            mesh_units(bad)
    ketchup = shared_data / "hope_ketchup" / "textured.obj"
    models = load_models(["Can", "Ketchup"], [f"Can={grocery['Can']}", f"Ketchup={ketchup}"],
                         mesh_units={"Can": "m"})  # Ketchup's .obj: cm by its suffix
    assert 0.08 < models["Can"].diameter < 0.12 and 0.1 < models["Ketchup"].diameter < 0.3
    with pytest.raises(InputFileError, match="likely in cm"):  # one unit for both: a 15 m Ketchup is refused
        load_models(["Can", "Ketchup"], [f"Can={grocery['Can']}", f"Ketchup={ketchup}"], mesh_units="m")
