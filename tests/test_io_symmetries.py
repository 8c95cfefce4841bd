"""dope_hope.io.symmetries (declarations beside meshes or named, BOP tables, units, errors) and
the one resolution order (dope_hope.symmetry.resolve)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.io.symmetries import bop_table_declaration, model_info_declaration, read_declaration
from dope_hope.symmetry.resolve import resolve_symmetries
from dope_hope.symmetry.transforms import declaration_transforms, symmetries_from_models_info

FLIP_X = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 20, 0, 0, 0, 1]  # translation 20 (file units)
ENTRY = {"diameter": 90.0, "symmetries_discrete": [FLIP_X],
         "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [10, 0, 0]}]}


def test_bop_entry_is_kept_as_written(tmp_path):
    """A BOP table's entry (mm) is kept as written, the numbers the BOP toolkit computes on
    (symmetries_from_models_info); its discretization into metres equals the label
    sampling's (declaration_transforms: nearest rotation, metres) where both sample."""
    path = tmp_path / "models_info.json"
    path.write_text(json.dumps({"3": ENTRY, "7": {"diameter": 50.0}}))
    decl = read_declaration(path, "mm", obj_id=3)
    assert decl.source == f"{path} [3]" and decl.diameter_m == pytest.approx(0.09)
    assert decl.entry == ENTRY and decl.units == "mm"
    # ceil(pi / (pi / 2)) = 2 steps of 180 degrees: the toolkit's and the 180-degree sampling agree
    np.testing.assert_allclose(symmetries_from_models_info(decl.entry, np.pi / 2, unit=decl.unit_m),
                               declaration_transforms(decl, step_deg=180.0), atol=1e-12)
    # units are the mesh's: the same entry beside a centimetre mesh moves ten times farther
    T_cm = declaration_transforms(read_declaration(path, "cm", obj_id=3), step_deg=90.0)
    T_mm = declaration_transforms(decl, step_deg=90.0)
    assert len(T_cm) == 8
    np.testing.assert_allclose(T_cm[:, :3, 3], 10.0 * T_mm[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(T_cm[4, :3, 3], [0.0, 0.0, 0.2])  # the flip's 20 cm


def test_declaration_beside_the_mesh(tmp_path, shared_data):
    """model_info.json beside the official DOPE sample meshes (metres), or a BOP table's entry
    beside obj_NNNNNN.ply (or for the given obj_id); none -> None."""
    cyl = shared_data / "symmetric_models" / "cylinder"
    decl = model_info_declaration(cyl / "textured.obj", units="m")
    assert decl.source == str(cyl / "model_info.json") and decl.units == "m"
    assert len(declaration_transforms(decl, step_deg=90.0)) == 8  # 4 turns about z x (identity, flip)
    assert model_info_declaration(tmp_path / "thing.obj") is None
    assert bop_table_declaration(tmp_path / "obj_000002.ply") is None
    (tmp_path / "models_info.json").write_text(json.dumps({"1": {"diameter": 10}, "2": ENTRY}))
    assert bop_table_declaration(tmp_path / "obj_000002.ply").entry == ENTRY
    assert bop_table_declaration(tmp_path / "obj_000004.ply") is None  # not in the table
    assert bop_table_declaration(tmp_path / "textured.obj") is None  # which entry: unknown
    assert bop_table_declaration(tmp_path / "textured.obj", obj_id=2).units == "cm"


def test_one_resolution_order(tmp_path):
    """models_info.json's entry, then a named file, then model_info.json beside the mesh, then
    the demo box's, then the catalog category; a named file beside a BOP entry is refused."""
    flip = {"symmetries_discrete": [FLIP_X]}
    named = tmp_path / "mine.json"
    named.write_text(json.dumps(flip))
    table, single = tmp_path / "bop", tmp_path / "single"
    table.mkdir()
    single.mkdir()
    (table / "models_info.json").write_text(json.dumps({"2": ENTRY}))
    (table / "model_info.json").write_text(json.dumps(flip))
    (single / "model_info.json").write_text(json.dumps(flip))
    found = resolve_symmetries("obj_000002", table / "obj_000002.ply")
    assert found.from_bop_table and found.declaration.entry == ENTRY
    with pytest.raises(ConfigError, match="--symmetries for obj_000002 would be ignored"):
        resolve_symmetries("obj_000002", table / "obj_000002.ply", named)
    found = resolve_symmetries("Widget", single / "widget.obj", named)
    assert found.declaration.source == str(named) and found.declaration.units == "cm"
    assert resolve_symmetries("Widget", single / "widget.obj").describe() == f"declared in {single / 'model_info.json'}"
    assert resolve_symmetries("Widget", tmp_path / "widget.obj").describe() == "none"
    assert resolve_symmetries("demobox").describe() == "declared in dope_hope.demo_object"
    assert resolve_symmetries("Ketchup", tmp_path / "ketchup.obj").describe() == "bottle category"
    assert resolve_symmetries("Widget", None, named).declaration.units == "mm"


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
