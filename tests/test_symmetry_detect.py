"""Symmetries found on a mesh (dope_hope.symmetry.detect) and their place in the resolution order."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError
from dope_hope.io.symmetries import read_declaration
from dope_hope.symmetry.detect import SymmetryTolerance, axis_name, detect_mesh_file_symmetries, detect_symmetries
from dope_hope.symmetry.resolve import label_symmetries, resolve_symmetries
from dope_hope.symmetry.transforms import category_symmetries, declaration_transforms, symmetries_from_models_info


def _rotations(T: np.ndarray) -> np.ndarray:
    return np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)[:, :3, :3]


def _same_sets(a: np.ndarray, b: np.ndarray, atol: float = 1e-3) -> bool:
    """Two sets of (S, 3, 3) rotations hold the same elements (any order)."""
    if len(a) != len(b):
        return False
    return all(any(np.allclose(x, y, atol=atol) for y in b) for x in a)


def _covered(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    """Every transform of (S, 4, 4) ``a`` is near one of ``b`` (rotation and translation)."""
    return all(np.min(np.abs(b - T).reshape(len(b), -1).max(axis=1)) <= atol for T in a)


def _axes(found) -> list[tuple[str, int]]:
    return [(axis_name(f.axis), f.order) for f in found.found]


def test_box_of_three_extents_has_the_three_flips_of_bop():
    found = detect_symmetries(trimesh.creation.box(extents=(0.10, 0.06, 0.03)))
    assert _axes(found) == [("x", 2), ("y", 2), ("z", 2)] and not found.continuous
    # exactly the cuboid's group: 180 degrees about x, y and z (BOP lists them without the identity)
    assert _same_sets(_rotations(found.discrete), category_symmetries("cuboid")[1:, :3, :3])
    assert found.text().startswith("flip about x (mean 0.0 mm, max 0.0 mm)")


def test_square_section_box_turns_by_90_degrees_about_its_long_axis():
    found = detect_symmetries(trimesh.creation.box(extents=(0.05, 0.05, 0.12)))
    assert ("z", 4) in _axes(found) and ("x", 2) in _axes(found)
    quarter = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    rots = _rotations(found.discrete)
    assert len(rots) == 7  # the square's 8 symmetries (with the two diagonal flips) less the identity
    assert any(np.allclose(R, quarter, atol=1e-6) for R in rots)
    diagonal = Rotation.from_rotvec(np.pi * np.array([1, 1, 0]) / np.sqrt(2)).as_matrix()
    assert any(np.allclose(R, diagonal, atol=1e-6) for R in rots)
    assert found.extra_discrete == 2


def test_slightly_unequal_section_is_not_square():
    """5.0 x 5.4 cm: a quarter turn moves two faces by 2 mm (mean beyond 0.8 mm)."""
    found = detect_symmetries(trimesh.creation.box(extents=(0.050, 0.054, 0.12)))
    assert _axes(found) == [("x", 2), ("y", 2), ("z", 2)]
    loose = detect_symmetries(trimesh.creation.box(extents=(0.050, 0.054, 0.12)),
                              SymmetryTolerance(mean_m=0.003, max_m=0.01))
    assert ("z", 4) in _axes(loose)


def test_cylinder_is_continuous_about_its_axis_with_one_flip():
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.10, sections=64)
    found = detect_symmetries(mesh)
    assert len(found.continuous) == 1 and axis_name(found.continuous[0][0]) == "z"
    np.testing.assert_allclose(found.continuous[0][1], 0.0, atol=1e-9)
    assert len(found.discrete) == 1  # one flip; the others are it turned about z
    flip = found.discrete[0][:3, :3]
    np.testing.assert_allclose(flip @ [0, 0, 1], [0, 0, -1], atol=1e-9)
    assert _axes(found) == [("z", 0), ("x", 2)]


def test_cylinder_declaration_matches_the_category_group():
    """Turned so that its axis is y (the HOPE cylinders'): BOP's composition of the found
    fields gives the cylinder category's group."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.10, sections=64)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # axis z -> -y
    found = detect_symmetries(mesh)
    assert axis_name(found.continuous[0][0]) == "y"
    T = declaration_transforms(found.declaration("mm"), step_deg=90.0)
    assert _same_sets(_rotations(T), category_symmetries("cylinder", step_deg=90.0)[:, :3, :3])


def test_cone_is_continuous_without_a_flip():
    found = detect_symmetries(trimesh.creation.cone(radius=0.03, height=0.08, sections=64))
    assert _axes(found) == [("z", 0)]
    assert len(found.discrete) == 0
    # its axis passes through the box centre (mid-height), which BOP's offset records
    np.testing.assert_allclose(found.continuous[0][1], [0, 0, 0.04], atol=1e-6)


def _asymmetric() -> trimesh.Trimesh:
    body = trimesh.creation.box(extents=(0.10, 0.06, 0.04))
    bump = trimesh.creation.box(extents=(0.03, 0.02, 0.02))
    bump.apply_translation((0.02, 0.04, 0.01))
    knob = trimesh.creation.cylinder(radius=0.008, height=0.02, sections=24)
    knob.apply_translation((-0.03, -0.01, 0.03))
    return trimesh.util.concatenate([body, bump, knob])


def test_asymmetric_body_has_none():
    found = detect_symmetries(_asymmetric())
    assert not found.any and found.found == [] and found.text().startswith("none")
    assert found.entry() == {}


def test_a_mesh_modelled_tilted_is_found_on_its_principal_axes():
    mesh = trimesh.creation.box(extents=(0.10, 0.06, 0.03))
    R = Rotation.from_euler("xyz", [25, -40, 15], degrees=True).as_matrix()
    mesh.apply_transform(np.block([[R, np.array([[0.01], [0.02], [-0.01]])], [np.zeros((1, 3)), np.ones((1, 1))]]))
    found = detect_symmetries(mesh)
    assert len(found.found) == 3 and all(f.order == 2 for f in found.found)
    expected = np.stack([R @ C @ R.T for C in category_symmetries("cuboid")[1:, :3, :3]])
    assert _same_sets(_rotations(found.discrete), expected, atol=1e-2)


def test_declaration_round_trip_and_units(tmp_path):
    mesh = trimesh.creation.cone(radius=0.03, height=0.08, sections=64)
    found = detect_symmetries(mesh)
    path = tmp_path / "model_info.json"
    path.write_text(json.dumps(found.entry("mm")))
    read = read_declaration(path, "mm")
    np.testing.assert_allclose(declaration_transforms(read, 30.0), declaration_transforms(found.declaration("mm"), 30.0))
    np.testing.assert_allclose(found.entry("mm")["symmetries_continuous"][0]["offset"], [0, 0, 40.0], atol=1e-6)
    np.testing.assert_allclose(found.entry("cm")["symmetries_continuous"][0]["offset"], [0, 0, 4.0], atol=1e-6)


def test_tolerance_is_checked():
    with pytest.raises(ValueError):
        SymmetryTolerance(mean_m=0.0)
    with pytest.raises(ValueError):
        SymmetryTolerance(mean_m=0.002, max_m=0.001)


# ----------------------------------------------------------------- resolution order
def _write_mesh(folder: Path, mesh: trimesh.Trimesh, name: str = "widget.obj") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    mesh.export(path)
    return path


def test_resolution_detects_for_a_mesh_outside_the_catalog_after_every_declaration(tmp_path):
    cyl = _write_mesh(tmp_path / "a", trimesh.creation.cylinder(radius=0.03, height=0.1, sections=64))
    found = resolve_symmetries("Widget", cyl, units="m")
    assert found.detected is not None and found.declaration is not None
    assert found.describe().startswith("detected on the mesh: continuous about z")
    assert found.declaration.units == "mm"
    assert resolve_symmetries("Widget", cyl, units="m", detect=False).describe() == "none"
    # a file beside the mesh wins
    (tmp_path / "a" / "model_info.json").write_text(json.dumps({"symmetries_discrete": []}))
    beside = resolve_symmetries("Widget", cyl, units="m")
    assert beside.detected is None and beside.describe().startswith("declared in")
    # so does --symmetries
    named = tmp_path / "named.json"
    named.write_text(json.dumps({"symmetries_continuous": [{"axis": [0, 1, 0], "offset": [0, 0, 0]}]}))
    assert resolve_symmetries("Widget", cyl, named, units="m").declaration.source == str(named)
    # a HOPE object keeps its category (the paper's convention) whatever its mesh shows...
    ketchup_box = _write_mesh(tmp_path / "c", trimesh.creation.box(extents=get_object("Ketchup").size_array))
    assert resolve_symmetries("Ketchup", ketchup_box, units="m").describe() == "bottle category"
    # ...but a mesh whose box is not the catalog's is another object of that name
    carton = _write_mesh(tmp_path / "d", trimesh.creation.box(extents=(0.044, 0.044, 0.16)))
    other = resolve_symmetries("Milk", carton, units="m")
    assert other.category is None and other.describe().startswith("detected on the mesh: flip about x")
    assert resolve_symmetries("Milk", carton, units="m", detect=False).describe() == "cuboid category"
    # an asymmetric mesh: found none, and said so
    odd = _write_mesh(tmp_path / "b", _asymmetric())
    none = resolve_symmetries("Widget", odd, units="m")
    assert none.declaration is None and none.describe().startswith("detected on the mesh: none")


def test_auto_labels_use_what_the_mesh_shows(tmp_path):
    box = _write_mesh(tmp_path / "box", trimesh.creation.box(extents=(0.10, 0.06, 0.03)))
    T, source = label_symmetries("auto", "Widget", mesh=box, units="m")
    assert _same_sets(_rotations(T), category_symmetries("cuboid")[:, :3, :3])
    assert source.startswith("detected on the mesh: flip about x")
    odd = _write_mesh(tmp_path / "odd", _asymmetric())
    T, source = label_symmetries("auto", "Widget", mesh=odd, units="m")
    np.testing.assert_allclose(T, np.eye(4)[None])  # nothing to relabel with: the labels stay
    with pytest.raises(ConfigError, match="no mesh"):
        label_symmetries("auto", "Widget")


def test_file_results_are_cached_by_content(tmp_path):
    path = _write_mesh(tmp_path, trimesh.creation.box(extents=(60.0, 40.0, 20.0)))
    first = detect_mesh_file_symmetries(path, "mm")
    t0 = time.perf_counter()
    again = detect_mesh_file_symmetries(path, "mm")
    assert again is first and time.perf_counter() - t0 < 0.05
    assert detect_mesh_file_symmetries(path, "cm") is not first  # another unit, another mesh
    path.write_bytes(path.read_bytes().replace(b"30", b"32", 1))  # new content, new answer
    assert detect_mesh_file_symmetries(path, "mm") is not first


# ----------------------------------------------------------------- the shared meshes
def test_shared_symmetric_models_match_their_model_info(shared_data):
    for name in ("cylinder", "hex_screw"):
        folder = shared_data / "symmetric_models" / name
        mesh_path = folder / "textured.obj"
        found = detect_mesh_file_symmetries(mesh_path, "m")
        declared = json.loads((folder / "model_info.json").read_text())
        assert len(found.continuous) == len(declared.get("symmetries_continuous", [])), name
        assert len(found.discrete) == len(declared.get("symmetries_discrete", [])), name
        # the same transforms as BOP discretizes them (metres; 0.866 in the file: 1e-3)
        ours = symmetries_from_models_info(found.entry("m"), unit=1.0)
        theirs = symmetries_from_models_info(declared, unit=1.0)
        assert _covered(ours, theirs, 2e-3) and _covered(theirs, ours, 2e-3), name


@pytest.mark.parametrize("name, expected", [
    ("Can", [("z", 0), ("x", 2)]),       # near-continuous about its axis (the opening: 7 mm), a flip
    ("Lemon", [("x", 0), ("y", 2)]),     # near-continuous about its long axis, a flip
    ("Cereal", [("x", 2), ("y", 2), ("z", 2)]),
    ("Milk", [("z", 2)]),                # the carton's spout: only a half turn about its long axis
    ("Bread", [("z", 2)]),
])
def test_grocery_meshes(shared_data, name, expected):
    path = shared_data / "grocery_objects" / name / "textured.obj"
    t0 = time.perf_counter()
    found = detect_mesh_file_symmetries(path, "m")
    seconds = time.perf_counter() - t0
    assert _axes(found) == expected, found.text()
    assert seconds < 5.0  # about 0.2-0.8 s on 2 busy cores


def test_hope_ketchup_mesh_shows_its_bottle_category(ketchup_obj):
    found = detect_mesh_file_symmetries(ketchup_obj, "cm")
    assert _axes(found) == [("y", 2)]
    assert _same_sets(_rotations(found.discrete), category_symmetries("bottle")[1:, :3, :3])
