"""`dope-hope import-official`: object from the file name, outputs, several files, mesh size, errors.

To keep the test fast the importer's architecture is a tiny lite network instead of the 50 M
parameter DOPE-DR-50 (``load_config`` patched in dope_hope.model.checkpoint); the real
DR-50 import is covered by tests/test_checkpoint.py and tests/test_predictor.py.
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
    assert rc == 2 and "unknown HOPE object" in err
    lite_ckpt = tmp_path / "Mayo.pth"
    torch.save({"module.nonsense": torch.zeros(3)}, lite_ckpt)
    rc, _, err = _run(["import-official", lite_ckpt])
    assert rc == 2 and "Mayo.pth" in err and len(err.strip().splitlines()) == 1
