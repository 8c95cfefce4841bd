"""dope_hope.io.models_dir: the one mesh lookup (explicit --mesh, then a models folder)."""
from __future__ import annotations

from pathlib import Path

import pytest

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.io.models_dir import (
    bop_obj_id,
    class_of_mesh,
    find_object_mesh,
    parse_mesh_args,
)


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    return path


def test_hope_and_bop_layouts_case_insensitive(tmp_path):
    hope = tmp_path / "hope"
    textured = _touch(hope / "Ketchup" / "textured.obj")
    _touch(hope / "Ketchup" / "a_first_by_name.obj")
    assert find_object_mesh("ketchup", hope) == textured
    flat = tmp_path / "flat"
    _touch(flat / "milk.OBJ")
    assert find_object_mesh("Milk", flat) == flat / "milk.OBJ"
    bop = tmp_path / "bop"
    ply = _touch(bop / "obj_000011.ply")
    assert find_object_mesh("Ketchup", bop) == ply
    assert find_object_mesh("obj_000030", _touch(bop / "obj_000030.ply").parent) == bop / "obj_000030.ply"


def test_search_order(tmp_path):
    """obj_NNNNNN.ply, <Name>/textured.obj, <Name>.obj, <Name>.ply, <Name>/*.obj, <Name>/*.ply."""
    d = tmp_path / "m"
    files = [d / "Ketchup" / "z.ply", d / "Ketchup" / "b.obj", d / "Ketchup.ply", d / "Ketchup.obj",
             d / "Ketchup" / "textured.obj", d / "obj_000011.ply"]
    for f in files:
        _touch(f)
        assert find_object_mesh("Ketchup", d) == f
    # a custom object: its name only
    assert find_object_mesh("DemoBox", _touch(d / "DemoBox.obj").parent) == d / "DemoBox.obj"


def test_explicit_mesh_wins_and_missing_ones_are_user_errors(tmp_path):
    d = tmp_path / "m"
    _touch(d / "obj_000011.ply")
    mine = tmp_path / "mine.obj"
    assert find_object_mesh("Ketchup", d, {"Ketchup": mine}) == mine
    assert find_object_mesh("Mustard", d, {"Ketchup": mine}, required=False) is None
    with pytest.raises(InputFileError, match=r"m: no mesh for Mustard \(looked for obj_000016\.ply, "
                                             r"Mustard/textured\.obj, Mustard\.obj, Mustard\.ply, "
                                             r"Mustard/\*\.obj\|ply\)"):
        find_object_mesh("Mustard", d)
    with pytest.raises(InputFileError, match="models folder not found"):
        find_object_mesh("Ketchup", tmp_path / "nope")


def test_class_of_a_mesh_file(tmp_path):
    assert class_of_mesh(tmp_path / "Ketchup" / "textured.obj") == "Ketchup"
    assert class_of_mesh(tmp_path / "meshes" / "hope-ketchup.obj") == "Ketchup"
    assert class_of_mesh(tmp_path / "models" / "obj_000011.ply") == "Ketchup"
    assert class_of_mesh(tmp_path / "models" / "obj_000030.ply") == "obj_000030"
    assert class_of_mesh(tmp_path / "thing.obj") is None
    assert bop_obj_id("ketchup") == 11 and bop_obj_id("obj_000030") == 30 and bop_obj_id("DemoBox") is None


def test_mesh_args(tmp_path):
    assert parse_mesh_args(["ketchup=a.obj", str(tmp_path / "Milk.ply")], ["Ketchup", "Milk"]) == {
        "Ketchup": Path("a.obj"), "Milk": tmp_path / "Milk.ply"}
    assert parse_mesh_args([str(tmp_path / "box.obj")], ["DemoBox"]) == {"DemoBox": tmp_path / "box.obj"}
    with pytest.raises(ConfigError, match=r"--mesh .*box\.obj: cannot tell which object"):
        parse_mesh_args([str(tmp_path / "box.obj")], ["DemoBox", "Ketchup"])


def test_new_object_meshes_name_each_file(tmp_path):
    from dope_hope.io.models_dir import new_object_meshes

    can = tmp_path / "Can" / "textured.obj"
    found = new_object_meshes([can, f"Bottle={tmp_path / 'b.obj'}", tmp_path / "my_widget.ply"])
    assert found == {"Can": can, "Bottle": tmp_path / "b.obj", "my_widget": tmp_path / "my_widget.ply"}
    with pytest.raises(ConfigError, match="is Can too; name each object"):
        new_object_meshes([can, f"can={tmp_path / 'other.obj'}"])
    with pytest.raises(ConfigError, match="name the object before '='"):
        new_object_meshes([f"={can}"])
    folder = tmp_path / "meshes"
    (folder / "Can").mkdir(parents=True)
    (folder / "Can" / "textured.obj").write_text("v 0 0 0\n")
    (folder / "Bottle.ply").write_text("ply\n")
    assert new_object_meshes([folder]) == {"Bottle": folder / "Bottle.ply", "Can": folder / "Can" / "textured.obj"}
