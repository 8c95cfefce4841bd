"""Several objects, BOP training data, mesh units and resume at their edges, through the CLI:
a metres mesh read as centimetres, a mesh paired with the wrong object, an object the data
never shows, flags a resume cannot honour, two models of one object, a unit for an object the
run does not have, a BOP set without visible masks or with masks of the wrong size, an empty
Isaac ROS version. Each ends in one line and exit 2 with nothing written, or (two models of
one object) the right result with a warning saying what was assumed.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_cli_mistakes import (  # noqa: F401 - fixtures
    TINY_SET,
    frames,
    mesh,
    no_temporaries,
    one_line_error,
    predictions,
    run_cli,
    weights,
)

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.geometry import cuboid_keypoints, intrinsics_matrix, project_points
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.io.meshes import load_mesh, mesh_cuboid

FW, FH = 80, 64
TRAIN = ["--init", "none", "--steps", 1, "--no-progress", "--set", *TINY_SET, "train.plots=false",
         "train.val_fraction=0.25"]


@pytest.fixture(scope="module")
def grocery(shared_data) -> Path:
    """The grocery models folder (``<Name>/textured.obj``, metres)."""
    return shared_data / "grocery_objects"


def _box(grocery: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    return mesh_cuboid(load_mesh(grocery / name / "textured.obj", units="m"))


def write_shelf_frames(folder: Path, grocery: Path, names: tuple[str, ...], n: int = 4,
                       record_size: bool = True) -> Path:
    """n tiny DOPE frames, each showing every object of ``names`` (grocery boxes, metres);
    ``record_size``: each frame's JSON records the boxes (as synth writes them)."""
    rng = np.random.default_rng(1)
    K = intrinsics_matrix(1.2 * FW, 1.2 * FW, (FW - 1) / 2, (FH - 1) / 2)
    folder.mkdir(parents=True, exist_ok=True)
    boxes = {name: _box(grocery, name) for name in names}
    for i in range(n):
        objects = []
        for k, name in enumerate(names):
            R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            t = np.array([0.08 * (k - (len(names) - 1) / 2), 0.0, 0.45])
            objects.append(ObjectAnnotation(name, R, t, project_points(cuboid_keypoints(*boxes[name]), K, R, t), 1.0))
        write_rgb(folder / f"{i:06d}.png", rng.integers(0, 255, (FH, FW, 3), dtype=np.uint8))
        extra = {"cuboid": [{"class": name, "size_m": boxes[name][0].tolist(), "center_m": boxes[name][1].tolist()}
                            for name in names]} if record_size else None
        write_dope_json(folder / f"{i:06d}.json", FrameAnnotation(folder / f"{i:06d}.json", K, FW, FH, objects),
                        extra=extra)
    return folder


@pytest.fixture(scope="module")
def shelf(tmp_path_factory, grocery) -> Path:
    """Frames of Can and Cereal that record their boxes."""
    return write_shelf_frames(tmp_path_factory.mktemp("shelf") / "frames", grocery, ("Can", "Cereal"))


@pytest.fixture(scope="module")
def plain_cans(tmp_path_factory, grocery) -> Path:
    """Frames of the Can that record no size: only their projected cuboids and poses say it."""
    return write_shelf_frames(tmp_path_factory.mktemp("plain") / "frames", grocery, ("Can",), record_size=False)


# ============================================================================= 1. mesh units
@pytest.mark.parametrize("command", ["synth", "synth-two", "train", "infer", "evaluate"])
def test_a_metres_mesh_read_as_centimetres_is_refused_with_the_likely_unit(command, grocery, shelf, frames, weights,
                                                                          predictions, tmp_path, capsys):
    can = grocery / "Can" / "textured.obj"
    out = tmp_path / "out"
    argv = {
        "synth": ["synth", "--mesh", can, "--out", out, "--count", 1, "--size", "32x32", "--no-progress"],
        "synth-two": ["synth", "--mesh", can, grocery / "Milk" / "textured.obj", "--out", out, "--count", 1,
                      "--size", "32x32", "--no-progress"],
        "train": ["train", "--data", shelf, "--object", "Can", "--mesh", can, "--out", out, *TRAIN],
        "infer": ["infer", frames / "000000.png", "--weights", weights, "--mesh", can, "--out", out, "--no-progress"],
        "evaluate": ["evaluate", "-p", predictions, "-d", frames, "--mesh", f"DemoBox={can}", "--out", out,
                     "--no-progress"],
    }[command]
    line = one_line_error(*run_cli(argv, capsys)[::2], command.split("-")[0])
    assert (f"{can}: mesh box 0.05 x 0.05 x 0.08 cm (read in cm) is too small for an object (largest side "
            f"under 5 mm); the file is likely in m: give its unit as m") in line
    assert not out.exists()


def test_bop_submit_refuses_a_models_folder_read_in_the_wrong_unit(tmp_path, monkeypatch):
    """bop-submit reads BOP models in millimetres: a model exported in metres is refused."""
    from test_cli_bop_submit import KETCHUP, _patch_backend, _run

    _patch_backend(monkeypatch)
    models = tmp_path / "models"
    models.mkdir()
    model = models / f"obj_{KETCHUP.obj_id:06d}.ply"
    trimesh.creation.box(extents=KETCHUP.size_array).export(model)  # metres, not BOP's mm
    root = tmp_path / "bop"
    (root / "hope" / "test" / "000001" / "rgb").mkdir(parents=True)
    out = tmp_path / "m_hope-test.csv"
    code, _, err = _run(["bop-submit", "--bop-root", root, "--weights", "k.pt", "--models-dir", models,
                         "--out", out, "--no-progress"])
    line = one_line_error(code, err, "bop-submit")
    assert f"{model}: mesh box " in line and "(read in mm) is too small for an object (largest side under 5 mm); " \
        "the file is likely in m: give its unit as m" in line
    assert not out.exists()


# ============================================================================= 2. mesh vs annotations
def test_train_mesh_off_by_a_unit_from_the_recorded_size_is_refused(grocery, shelf, tmp_path, capsys):
    """A Can in millimetres read as centimetres is a plausible 50 cm can, but the frames record
    a 5 cm one: refused, naming the mesh, both sizes and the unit the file is likely in."""
    can_mm = tmp_path / "can_mm.ply"
    trimesh.Trimesh(load_mesh(grocery / "Can" / "textured.obj", units="m").vertices * 1000.0,
                    load_mesh(grocery / "Can" / "textured.obj", units="m").faces).export(can_mm)
    out = tmp_path / "run"
    argv = ["train", "--data", shelf, "--object", "Can", "--mesh", can_mm, "--units", "cm", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    size = _box(grocery, "Can")[0]
    assert f"--mesh {can_mm}: mesh box {np.round(size * 1000, 2).tolist()} cm does not match the size " \
           f"000000.json records {np.round(size * 100, 2).tolist()} cm for Can (the file is likely in mm, " \
           "not cm: give its unit as mm (--units mm))" in line
    assert not out.exists()


def test_train_mesh_of_another_object_than_the_projected_cuboids_is_refused(grocery, plain_cans, tmp_path, capsys):
    """Frames that record no size: the box their projected cuboids imply (with their poses)
    is the reference; the cereal box's mesh for the Can is refused."""
    cereal = grocery / "Cereal" / "textured.obj"
    out = tmp_path / "run"
    argv = ["train", "--data", plain_cans, "--object", "Can", "--mesh", cereal, "--units", "m", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    can = np.sort(_box(grocery, "Can")[0])
    assert f"--mesh {cereal}: mesh box {np.round(_box(grocery, 'Cereal')[0] * 100, 2).tolist()} cm does not " \
           "match the box the annotated projected cuboids imply (3 instances, e.g. in 000000.json) " in line
    assert f"{np.round(can * 100, 2).tolist()} cm for Can (wrong object or wrong mesh units?)" in line
    assert not out.exists()


# ============================================================================= 3. NAME=PATH
@pytest.mark.parametrize("mesh_args, expected", [
    (["Cereal={m}/Cereal/textured.obj"], "--mesh Cereal={m}/Cereal/textured.obj: Cereal is not an object of this "
                                         "run (objects: Can)"),
    (["{m}/Cereal/textured.obj", "{m}/Can/textured.obj"], "--mesh {m}/Cereal/textured.obj: its name says Cereal, "
                                                          "but it pairs with Can (the meshes pair with the objects "
                                                          "in order: Can, Cereal); write --mesh NAME=PATH"),
])
def test_train_mesh_named_for_another_object_is_refused(mesh_args, expected, grocery, shelf, tmp_path, capsys):
    objects = ["Can"] if len(mesh_args) == 1 else ["Can", "Cereal"]
    out = tmp_path / "run"
    argv = ["train", "--data", shelf, "--object", *objects, "--mesh", *[a.format(m=grocery) for a in mesh_args],
            "--units", "m", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert expected.format(m=grocery) in line
    assert not out.exists()


@pytest.mark.parametrize("flag, value, expected", [
    ("--mesh", "Banana={mesh}", "--mesh Banana={mesh}: Banana is not an object of this run (objects: DemoBox)"),
    ("--symmetries", "Banana={info}", "--symmetries Banana={info}: Banana is not an object of this run "
                                      "(objects: DemoBox)"),
])
def test_evaluate_name_that_is_no_object_of_the_run_is_refused(flag, value, expected, frames, predictions, mesh,
                                                               tmp_path, capsys):
    names = {"mesh": mesh, "info": mesh.parent / "model_info.json"}
    out = tmp_path / "e"
    argv = ["evaluate", "-p", predictions, "-d", frames, flag, value.format(**names), "--out", out, "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    assert expected.format(**names) in line
    assert not out.exists()


# ============================================================================= 7. --mesh-units NAME=UNIT
@pytest.mark.parametrize("units", [["Banana=m"], ["all=cm", "Banana=m"]])
def test_evaluate_mesh_units_for_an_unknown_object_is_refused(units, frames, predictions, mesh, tmp_path, capsys):
    out = tmp_path / "e"
    argv = ["evaluate", "-p", predictions, "-d", frames, "--mesh", mesh, "--out", out, "--no-progress"]
    for u in units:
        argv += ["--mesh-units", u]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    assert "--mesh-units Banana=m: Banana is not an object of this run (objects: DemoBox)" in line
    assert not out.exists()


# ============================================================================= 4. an object the data lacks
def test_train_object_with_no_instance_in_the_data_is_refused(shelf, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "--data", shelf, "--object", "Can", "Milk", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert (f"{shelf}: no annotated instance of Milk (--object), whose maps would only learn 'absent'; "
            "instances found: Can 4") in line
    assert not out.exists()


# ============================================================================= 5. resume
@pytest.fixture(scope="module")
def shelf_run(tmp_path_factory, shelf, grocery) -> Path:
    """A finished one-step run of Can + Cereal (the legitimate input: meshes in metres, said)."""
    out = tmp_path_factory.mktemp("run") / "shelf"
    from dope_hope import cli

    code = cli.main([str(a) for a in ["train", "--data", shelf, "--object", "Can", "Cereal", "--models-dir", grocery,
                                      "--units", "m", "--out", out, *TRAIN]])
    assert code == 0 and (out / "last.pt").is_file()
    return out


@pytest.mark.parametrize("flags, expected", [
    (["--object", "Can", "Milk"], "--object Can Milk: --resume continues {run}/last.pt, a run of Can, Cereal, whose "
                                  "objects it cannot change; drop --object, or start a new run (another --out)"),
    (["--object", "Cereal", "Can"], "--object Cereal Can: --resume continues {run}/last.pt, a run of Can, Cereal"),
    (["--backbone-weights", "vgg.pth"], "--backbone-weights vgg.pth: --resume continues {run}/last.pt with its own "
                                        "weights; give one of them"),
])
def test_resume_refuses_flags_it_cannot_honour(flags, expected, shelf_run, tmp_path, capsys):
    before = {p.name: p.read_bytes() for p in shelf_run.iterdir() if p.is_file()}
    argv = ["train", "--out", shelf_run, "--resume", "--steps", 2, "--no-progress", *flags]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert expected.format(run=shelf_run) in line
    assert {p.name: p.read_bytes() for p in shelf_run.iterdir() if p.is_file()} == before


def test_resume_with_its_own_objects_continues(shelf_run, tmp_path, capsys):
    run = tmp_path / "again"
    shutil.copytree(shelf_run, run)
    code, out, err = run_cli(["train", "--out", run, "--resume", "--object", "can", "cereal", "--steps", 2,
                              "--no-progress"], capsys)
    assert code == 0, err
    assert out.startswith("completed: step 2 ")


# ============================================================================= 5b. meshes of a two-object model
def test_infer_takes_a_mesh_and_a_unit_per_object_of_a_model(shelf_run, shelf, grocery, tmp_path, capsys):
    """--mesh NAME=PATH / --mesh-units NAME=UNIT (as evaluate takes them): each object of one
    model gets its own mesh (its box and surface), an object left out keeps its cuboid."""
    from dope_hope.inference.model_set import build_predictors, stream_tracker
    from dope_hope.inference.tracking import class_symmetry_transforms

    can, cereal = grocery / "Can" / "textured.obj", grocery / "Cereal" / "textured.obj"
    (p,) = build_predictors([shelf_run / "last.pt"], [Path(f"can={can}"), Path(f"Cereal={cereal}")],
                            mesh_units={"Can": "m", "": "m"})
    by_name = {o.class_name: o for o in p.objects}
    for name in ("Can", "Cereal"):
        assert by_name[name].mesh is not None
        np.testing.assert_allclose(by_name[name].cuboid_size_m, _box(grocery, name)[0])
    assert (by_name["Can"].mesh_file, by_name["Can"].mesh_units) == (can, "m")
    # --track: the tracker reads each object's symmetries from the file its predictor read, in its unit
    tracker = stream_tracker([p])
    np.testing.assert_array_equal(tracker.symmetries["Can"], class_symmetry_transforms("Can", can, "m"))
    np.testing.assert_array_equal(tracker.symmetries["Cereal"], class_symmetry_transforms("Cereal", cereal, "m"))
    (only_can,) = build_predictors([shelf_run / "last.pt"], [Path(f"Can={can}")], mesh_units={"Can": "m"})
    assert [o.mesh is not None for o in only_can.objects] == [True, False]
    assert [o.mesh_file for o in only_can.objects] == [can, None]
    out = tmp_path / "out"
    code, _, err = run_cli(["infer", shelf / "000000.png", "--weights", shelf_run / "last.pt", "--mesh", f"Can={can}",
                            "--mesh", f"Cereal={cereal}", "--mesh-units", "m", "--out", out, "--no-overlay",
                            "--no-progress"], capsys)
    assert code == 0, err
    assert (out / "predictions.jsonl").is_file()


@pytest.mark.parametrize("flags, expected", [
    (["--mesh", "Milk={grocery}/Milk/textured.obj"],
     "--mesh Milk={grocery}/Milk/textured.obj: Milk is not an object of this run (objects: Can, Cereal)"),
    (["--mesh", "Can={grocery}/Can/textured.obj", "--mesh-units", "Milk=m"],
     "--mesh-units Milk=m: Milk is not an object of this run (objects: Can, Cereal)"),
    (["--mesh", "{grocery}/Can/textured.obj"],
     "--mesh {grocery}/Can/textured.obj: {run}/last.pt detects 2 objects (Can, Cereal); give --mesh NAME=PATH "
     "per object, or a models folder"),
])
def test_infer_mesh_of_no_object_of_the_model_is_refused(flags, expected, shelf_run, shelf, grocery, tmp_path,
                                                         capsys):
    out = tmp_path / "out"
    argv = ["infer", shelf / "000000.png", "--weights", shelf_run / "last.pt",
            *[f.format(grocery=grocery) for f in flags], "--out", out, "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert expected.format(grocery=grocery, run=shelf_run) in line
    assert not out.exists()


# ============================================================================= 6. two models, one object
@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(model A, a copy B, the image it detects its box in, K.json)."""
    from fitted_model import IMAGE_HW, K, fit_lite_checkpoint, scene

    folder = tmp_path_factory.mktemp("fitted")
    a = fit_lite_checkpoint(folder / "a.pt")
    b = folder / "b.pt"
    shutil.copy(a, b)
    rgb, _ = scene()
    write_rgb(folder / "scene.png", rgb)
    (folder / "K.json").write_text(json.dumps({"K": K.tolist(), "width": IMAGE_HW[1], "height": IMAGE_HW[0]}))
    return a, b, folder


def test_two_models_of_the_same_object_report_it_once_from_the_first(fitted, tmp_path, capsys):
    a, b, folder = fitted
    common = [folder / "scene.png", "--camera", folder / "K.json", "--no-progress", "--no-overlay", "--min-score", 0]
    code, one, err = run_cli(["infer", *common, "--weights", a, "--out", tmp_path / "one"], capsys)
    assert code == 0, err
    single = [json.loads(ln) for ln in one.splitlines()]
    assert single and all(r["class"] == "Ketchup" for r in single)
    code, two, err = run_cli(["infer", *common, "--weights", a, "--weights", b, "--out", tmp_path / "two"], capsys)
    assert code == 0, err
    warnings = [ln for ln in err.splitlines() if ": warning: " in ln]
    assert warnings == [f"dope-hope infer: warning: Ketchup is in both {a} and {b}: reported from {a} only "
                        "(the first --weights holding it)"]
    untimed = [{k: v for k, v in json.loads(ln).items() if k != "time"} for ln in two.splitlines()]
    assert untimed == [{k: v for k, v in r.items() if k != "time"} for r in single]  # not twice


# ============================================================================= 8, 9. BOP training sets
@pytest.fixture(scope="module")
def bop_split(tmp_path_factory, grocery) -> Path:
    """A one-image BOP split of the Can (obj_id 1): rgb, mask, mask_visib, models_info.json."""
    root = tmp_path_factory.mktemp("bop")
    size, center = _box(grocery, "Can")
    scene = root / "train_pbr" / "000000"
    K = intrinsics_matrix(1.2 * FW, 1.2 * FW, (FW - 1) / 2, (FH - 1) / 2)
    R, t = Rotation.from_euler("xyz", [30, 20, 10], degrees=True).as_matrix(), np.array([0.0, 0.0, 0.4])
    for sub in ("rgb", "mask", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    write_rgb(scene / "rgb" / "000000.png", np.full((FH, FW, 3), 120, np.uint8))
    uv = project_points(cuboid_keypoints(size, center), K, R, t)
    mask = np.zeros((FH, FW, 3), np.uint8)
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    mask[max(y0, 0):y1, max(x0, 0):x1] = 255
    write_rgb(scene / "mask" / "000000_000000.png", mask)
    write_rgb(scene / "mask_visib" / "000000_000000.png", mask)
    (scene / "scene_gt.json").write_text(json.dumps({"0": [{"obj_id": 1, "cam_R_m2c": R.reshape(-1).tolist(),
                                                            "cam_t_m2c": (t * 1000).tolist()}]}))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K.reshape(-1).tolist(), "depth_scale": 1.0}}))
    lo = (center - size / 2) * 1000
    (root / "models").mkdir()
    (root / "models" / "models_info.json").write_text(json.dumps({"1": {
        "diameter": float(np.linalg.norm(size) * 1000), **{f"min_{a}": float(v) for a, v in zip("xyz", lo)},
        **{f"size_{a}": float(v) for a, v in zip("xyz", size * 1000)}}}))
    return root / "train_pbr"


def _bop_copy(bop_split: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "ds"
    shutil.copytree(bop_split.parent, copy)
    return copy / "train_pbr"


def test_bop_training_set_without_mask_visib_is_refused_naming_the_folder(bop_split, tmp_path, capsys):
    split = _bop_copy(bop_split, tmp_path)
    shutil.rmtree(split / "000000" / "mask_visib")
    out = tmp_path / "run"
    argv = ["train", "--data", split, "--object", "obj_000001", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert (f"{split / '000000' / 'mask_visib'}: missing: the visibility of each instance comes from mask_visib/ "
            "(or scene_gt_info.json's visib_fract), and this scene has neither") in line
    assert not out.exists()


@pytest.mark.parametrize("folder", ["mask_visib", "mask"])
def test_bop_mask_of_the_wrong_size_is_refused_naming_the_file(folder, bop_split, tmp_path, capsys):
    split = _bop_copy(bop_split, tmp_path)
    bad = split / "000000" / folder / "000000_000000.png"
    write_rgb(bad, np.full((FH // 2, FW // 2, 3), 255, np.uint8))
    out = tmp_path / "run"
    argv = ["train", "--data", split, "--object", "obj_000001", "--out", out, *TRAIN]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert f"{bad}: mask is {FW // 2}x{FH // 2} pixels, its image {FW}x{FH}" in line
    assert not out.exists()


def test_bop_training_set_with_its_masks_trains(bop_split, tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", bop_split, "--val", bop_split, "--object", "obj_000001", "--out", out,
                            *TRAIN[:-1], "train.batch_size=1"], capsys)
    assert code == 0, err
    assert json.loads((out / "summary.json").read_text())["train_frames"] == 1


# ============================================================================= 10. export
def test_empty_isaac_ros_version_is_refused(weights, tmp_path, capsys):
    argv = ["export", "--weights", weights, "--out", tmp_path / "m.onnx", "--layout", "isaac-ros",
            "--isaac-ros-version", ""]
    line = one_line_error(*run_cli(argv, capsys)[::2], "export")
    assert "--isaac-ros-version must look like 3.1 or 4.0, got ''" in line
    assert list(tmp_path.iterdir()) == []
