"""`dope-hope import-official`: object from the file name, outputs, several files, mesh size, errors.

To keep the test fast the importer's architecture is a tiny lite network instead of the 50 M
parameter DOPE-DR-50 (``load_config`` patched in dope_hope.model.checkpoint); the real
DR-50 import is covered by tests/test_model_checkpoint.py and tests/test_inference_predictor.py.
"""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from dope_hope import cli
from dope_hope.catalog import get_object
from dope_hope.model import build_model
from dope_hope.model.checkpoint import load_checkpoint

torch.set_num_threads(1)
TINY = {"model": {"arch": "lite", "head": 50, "stages": 1,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}


def _run(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(autouse=True)
def tiny_architecture(monkeypatch):
    monkeypatch.setattr("dope_hope.model.checkpoint.load_config", lambda name: dict(TINY))


def _official(path: Path) -> Path:
    """An "official" file: a bare state dict with the DataParallel ``module.`` prefix."""
    torch.save({f"module.{k}": v for k, v in build_model(TINY).state_dict().items()}, path)
    return path


def test_object_from_file_name_legacy_frame_and_default_output(tmp_path):
    pth = _official(tmp_path / "Ketchup.pth")
    rc, out, err = _run(["import-official", pth])
    assert rc == 0, err
    ckpt = load_checkpoint(tmp_path / "Ketchup.pt")
    assert ckpt["object"]["class_name"] == "Ketchup" and ckpt["object"]["frame"] == "legacy"
    assert ckpt["keypoint_order"] == "dope-legacy"
    assert ckpt["object"]["size_m"] == pytest.approx(list(get_object("Ketchup").size_array))
    assert "Ketchup.pt" in out and "(catalog)" in out
    # the result is what every other command takes: a predictor opens it
    from dope_hope.inference.predictor import DopePredictor

    assert DopePredictor(tmp_path / "Ketchup.pt").legacy


def test_several_files_into_a_folder_and_mesh_size(tmp_path):
    a, b = _official(tmp_path / "Mustard.pth"), _official(tmp_path / "BBQSauce.pth")
    rc, out, err = _run(["import-official", a, b, "--out", tmp_path / "imported"])
    assert rc == 0, err
    assert {p.name for p in (tmp_path / "imported").iterdir()} == {"Mustard.pt", "BBQSauce.pt"}
    assert load_checkpoint(tmp_path / "imported" / "BBQSauce.pt")["object"]["class_name"] == "BBQSauce"

    size = np.array([0.07, 0.15, 0.045])
    mesh = trimesh.creation.box(extents=size * 100.0)  # centimetres, as a HOPE OBJ
    mesh.export(tmp_path / "ketchup_mesh.obj")
    pth = _official(tmp_path / "dope_weights_final.pth")
    rc, out, err = _run(["import-official", pth, "--object", "ketchup", "--mesh", tmp_path / "ketchup_mesh.obj",
                         "--out", tmp_path / "k.pt"])
    assert rc == 0, err
    ckpt = load_checkpoint(tmp_path / "k.pt")
    assert ckpt["object"]["class_name"] == "Ketchup"
    assert ckpt["object"]["size_m"] == pytest.approx(size.tolist())
    assert "mesh ketchup_mesh.obj" in out


def test_errors_are_one_line(tmp_path):
    pth = _official(tmp_path / "weights.pth")
    rc, _, err = _run(["import-official", pth])
    assert rc == 2 and "--object" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "weights.pt").exists()
    rc, _, err = _run(["import-official", tmp_path / "Ketchup.pth"])
    assert rc == 2 and "weights file not found" in err
    rc, _, err = _run(["import-official", pth, "--object", "Banana"])
    assert rc == 2 and "'Banana' is not a HOPE object" in err and "--dimensions" in err
    rc, _, err = _run(["import-official", _official(tmp_path / "net_epoch_0060.pth")])
    assert rc == 2 and "cannot tell the object" in err and "--object" in err
    rc, _, err = _run(["import-official", pth, "--object", "Banana", "--dimensions", "3", "0", "19"])
    assert rc == 2 and "--dimensions: expected 3 positive sizes" in err
    with pytest.raises(SystemExit) as exc:
        _run(["import-official", pth, "--object", "Banana", "--dimensions", "3", "4", "19",
              "--mesh", tmp_path / "banana.obj"])
    assert exc.value.code == 2
    lite_ckpt = tmp_path / "Mayo.pth"
    torch.save({"module.nonsense": torch.zeros(3)}, lite_ckpt)
    rc, _, err = _run(["import-official", lite_ckpt])
    assert rc == 2 and "Mayo.pth" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("stem, name", [
    ("Ketchup", "Ketchup"), ("net_Ketchup_0060", "Ketchup"), ("final_net_Ketchup_0060", "Ketchup"),
    ("net_cracker_60", "cracker"), ("cracker_60", "cracker"), ("net_my_box_0012", "my_box"),
    ("net_epoch_0060", None)])
def test_object_names_of_official_files(stem, name):
    from dope_hope.model.checkpoint import official_object_name

    assert official_object_name(stem) == name


def test_training_script_names_and_dimensions(tmp_path):
    """net_<name>_<epoch>.pth of the official train.py: a HOPE name keeps the legacy frame
    (--dimensions in that frame, as in the official HOPE config); any other object gets the
    official cuboid frame, so its poses are those of NVIDIA's inference."""
    pth = _official(tmp_path / "net_Ketchup_0060.pth")
    rc, out, err = _run(["import-official", pth, "--dimensions", "14.8608", "4.3368", "6.4514"])
    assert rc == 0, err
    ckpt = load_checkpoint(tmp_path / "net_Ketchup_0060.pt")
    assert ckpt["object"]["class_name"] == "Ketchup" and ckpt["object"]["frame"] == "legacy"
    assert ckpt["object"]["size_m"] == pytest.approx([0.064514, 0.148608, 0.043368])  # mesh frame

    pth = _official(tmp_path / "net_cracker_0060.pth")
    rc, out, err = _run(["import-official", pth, "--dimensions", "16.4036", "21.3437", "7.18",
                         "--out", tmp_path / "cracker.pt"])
    assert rc == 0, err
    ckpt = load_checkpoint(tmp_path / "cracker.pt")
    assert ckpt["object"] == {"class_name": "cracker", "size_m": pytest.approx([0.164036, 0.213437, 0.0718]),
                              "frame": "mesh"}
    assert ckpt["keypoint_order"] == "dope-current"
    assert "poses of the official DOPE cuboid" in out
    from dope_hope.inference.predictor import DopePredictor

    pred = DopePredictor(tmp_path / "cracker.pt")
    assert not pred.legacy and pred.class_name == "cracker"
    # PnP runs on the official Cuboid3d (inference/cuboid.py: x right, y down, z forward;
    # front top right, front top left, ..., rear bottom right, centre), so the pose is its
    w, h, d = 0.164036, 0.213437, 0.0718
    right, left, top, bottom, front, rear = w / 2, -w / 2, -h / 2, h / 2, d / 2, -d / 2
    official = [[right, top, front], [left, top, front], [left, bottom, front], [right, bottom, front],
                [right, top, rear], [left, top, rear], [left, bottom, rear], [right, bottom, rear], [0, 0, 0]]
    np.testing.assert_allclose(pred.cuboid_pnp, official, atol=1e-12)
