"""dope_hope.io.symmetries: declarations beside meshes or named, BOP tables, units, errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dope_hope.evaluation import metrics
from dope_hope.errors import InputFileError
from dope_hope.io.symmetries import declared_symmetries, read_declaration

FLIP_X = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 20, 0, 0, 0, 1]  # translation 20 (file units)
ENTRY = {"diameter": 90.0, "symmetries_discrete": [FLIP_X],
         "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [10, 0, 0]}]}


def test_bop_entry_is_kept_as_written(tmp_path):
    """A BOP table's entry (mm) is kept as written, the numbers the BOP toolkit computes on
    (metrics.symmetries_from_models_info); its discretization into metres equals the
    label sampling's (parse_model_info: nearest rotation, metres) where both sample."""
    path = tmp_path / "models_info.json"
    path.write_text(json.dumps({"3": ENTRY, "7": {"diameter": 50.0}}))
    decl = read_declaration(path, "mm", obj_id=3)
    assert decl.source == f"{path} [3]" and decl.diameter_m == pytest.approx(0.09)
    assert decl.entry == ENTRY and decl.units == "mm"
    # ceil(pi / (pi / 2)) = 2 steps of 180 degrees: the toolkit's and the 180-degree sampling agree
    np.testing.assert_allclose(metrics.symmetries_from_models_info(decl.entry, np.pi / 2, unit=decl.unit_m),
                               decl.transforms(step_deg=180.0), atol=1e-12)
    # units are the mesh's: the same entry beside a centimetre mesh moves ten times farther
    T_cm = read_declaration(path, "cm", obj_id=3).transforms(step_deg=90.0)
    T_mm = decl.transforms(step_deg=90.0)
    assert len(T_cm) == 8
    np.testing.assert_allclose(T_cm[:, :3, 3], 10.0 * T_mm[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(T_cm[4, :3, 3], [0.0, 0.0, 0.2])  # the flip's 20 cm


def test_declaration_beside_the_mesh(tmp_path, shared_data):
    """model_info.json beside the official DOPE sample meshes (metres), or a BOP table beside
    obj_NNNNNN.ply; a named file wins; none -> None."""
    cyl = shared_data / "symmetric_models" / "cylinder"
    decl = declared_symmetries(mesh_path=cyl / "textured.obj", units="m")
    assert decl.source == str(cyl / "model_info.json") and decl.units == "m"
    assert len(decl.transforms(step_deg=90.0)) == 8  # 4 turns about z x (identity, flip)
    assert declared_symmetries(mesh_path=tmp_path / "thing.obj") is None
    (tmp_path / "models_info.json").write_text(json.dumps({"1": {"diameter": 10}, "2": ENTRY}))
    assert declared_symmetries(mesh_path=tmp_path / "obj_000002.ply").entry == ENTRY
    assert declared_symmetries(mesh_path=tmp_path / "obj_000004.ply") is None  # not in the table
    assert declared_symmetries(mesh_path=tmp_path / "textured.obj", obj_id=2).units == "cm"
    named = tmp_path / "mine.json"
    named.write_text(json.dumps({"symmetries_discrete": [FLIP_X]}))
    assert declared_symmetries(named, tmp_path / "obj_000002.ply").source == str(named)
    assert declared_symmetries(named).units == "mm"


@pytest.mark.parametrize("content, obj_id, message", [
    ({"1": ENTRY, "2": ENTRY}, None, "a models_info table of 2 objects"),
    ({"1": ENTRY}, 5, "no entry for obj_id 5"),
    ({"symmetries_discrete": [[1, 0, 0]]}, None, "symmetries_discrete[0]: expected shape (16,)"),
    ({"symmetries_discrete": [[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}, None,
     "symmetries_discrete[0]: the 3x3 block is not a rotation"),
    ({"symmetries_continuous": [{"axis": [0, 0, 0]}]}, None, "symmetries_continuous[0].axis: zero axis"),
])
def test_bad_declarations_name_the_file_and_field(tmp_path, content, obj_id, message):
    path = tmp_path / "model_info.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputFileError) as err:
        read_declaration(path, obj_id=obj_id)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)
