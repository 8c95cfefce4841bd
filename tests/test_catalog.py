"""dope_hope.catalog: the 28 objects, lookups, sizes against the Ketchup mesh, symmetry groups."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dope_hope.catalog import (
    CATEGORIES,
    HOPE_OBJECTS,
    VERTICAL_AXIS,
    get_object,
)
from dope_hope.errors import DopeHopeError, UnknownObjectError
from dope_hope.geometry import cuboid_keypoints, legacy_size_to_mesh
from dope_hope.io.meshes import load_mesh, mesh_cuboid
from dope_hope.symmetry.transforms import category_symmetries


def test_28_objects_with_bop_ids_in_alphabetical_order():
    assert len(HOPE_OBJECTS) == 28
    assert [o.obj_id for o in HOPE_OBJECTS] == list(range(1, 29))
    names = [o.name for o in HOPE_OBJECTS]
    assert names == sorted(names) and len(set(names)) == 28
    # spot checks against the BOP HOPE model ids
    assert get_object(1).name == "AlphabetSoup"
    assert get_object(11).name == "Ketchup"
    assert get_object(28).name == "Yogurt"


def test_categories_match_the_hope_paper_grouping():
    counts = {c: sum(o.category == c for o in HOPE_OBJECTS) for c in CATEGORIES}
    assert counts == {"cylinder": 12, "cuboid": 11, "bottle": 5}
    assert {o.name for o in HOPE_OBJECTS if o.category == "bottle"} == {
        "SaladDressing", "Mayo", "BBQSauce", "Ketchup", "Mustard"}


@pytest.mark.parametrize("key", ["Ketchup", "ketchup", "KETCHUP", 11, "11", np.int64(11)])
def test_get_object_by_name_or_id(key):
    assert get_object(key).name == "Ketchup"


def test_get_object_normalizes_display_names():
    assert get_object("Macaroni and Cheese").name == "MacaroniAndCheese"
    assert get_object("green_beans").name == "GreenBeans"
    assert get_object("BBQSauce").display_name == "BBQ Sauce"


@pytest.mark.parametrize("key", ["Ketchupp", 0, 29, "", "cracker"])
def test_unknown_objects_raise(key):
    with pytest.raises(UnknownObjectError) as err:
        get_object(key)
    assert isinstance(err.value, DopeHopeError)
    assert "\n" not in str(err.value)


def test_sizes_are_mesh_frame_metres_and_plausible():
    for o in HOPE_OBJECTS:
        size = o.size_array
        assert size.shape == (3,)
        assert np.all((size > 0.015) & (size < 0.26)), o.name
        assert o.diameter == pytest.approx(np.linalg.norm(size))
        assert o.size_source in ("dope-config", "estimate")
    # bottles and cans stand on y: their vertical (y) extent is the largest
    for o in HOPE_OBJECTS:
        if o.category == "bottle":
            assert np.argmax(o.size_array) == 1, o.name
    assert {o.name for o in HOPE_OBJECTS if o.size_source == "estimate"} == {
        "CreamCheese", "Parmesan", "Tuna"}


def test_ketchup_size_matches_the_mesh_within_half_a_millimetre(ketchup_obj):
    mesh = load_mesh(ketchup_obj)
    size, center = mesh_cuboid(mesh)
    ketchup = get_object("Ketchup")
    assert np.abs(size - ketchup.size_array).max() < 5e-4
    # the legacy config numbers [14.8608, 4.3368, 6.4514] cm are the same box
    legacy = np.array([14.8608, 4.3368, 6.4514]) / 100.0
    assert np.abs(legacy_size_to_mesh(legacy) - size).max() < 5e-4
    # y is the bottle's vertical, longest axis
    assert int(np.argmax(size)) == int(np.argmax(VERTICAL_AXIS)) == 1
    assert ketchup.diameter >= mesh.extents.max()


def test_symmetry_group_shapes_identity_first_and_rotations():
    expected = {"cylinder": 720, "cuboid": 4, "bottle": 2}
    for cat, n in expected.items():
        T = category_symmetries(cat)
        assert T.shape == (n, 4, 4)
        np.testing.assert_allclose(T[0], np.eye(4))
        R = T[:, :3, :3]
        np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0)
        np.testing.assert_allclose(T[:, :3, 3], 0.0)
        np.testing.assert_allclose(T[:, 3], np.broadcast_to([0, 0, 0, 1], (n, 4)))
    assert category_symmetries("cylinder", step_deg=90).shape == (8, 4, 4)
    assert category_symmetries(get_object("Tuna").category, step_deg=30).shape == (24, 4, 4)
    with pytest.raises(UnknownObjectError):
        category_symmetries("sphere")


def _max_nn(a: np.ndarray, b: np.ndarray) -> float:
    return float(cKDTree(b).query(a)[0].max())


def test_cylinder_symmetries_map_a_y_axis_cylinder_onto_itself():
    cyl = trimesh.creation.cylinder(radius=0.033, height=0.07, sections=36)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # z -> y
    assert int(np.argmax(np.abs(cyl.vertices).max(0))) == 1
    verts = np.unique(cyl.vertices, axis=0)
    T = category_symmetries("cylinder", step_deg=10.0)  # 10° divides the 36 sections
    assert max(_max_nn(verts @ S[:3, :3].T, verts) for S in T) < 1e-12
    # a quarter turn about x is not a symmetry of a cylinder taller than wide
    Rx = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3]
    assert _max_nn(verts @ Rx.T, verts) > 0.01


@pytest.mark.parametrize("category", ["cuboid", "bottle"])
def test_box_symmetries_map_the_box_onto_itself(category):
    size = get_object("Cookies").size_array
    box = trimesh.creation.box(extents=size)
    pts = trimesh.sample.sample_surface(box, 500, seed=0)[0]
    kp = cuboid_keypoints(size)
    for S in category_symmetries(category):
        moved = np.abs(pts @ S[:3, :3].T)
        # surface samples stay on the box's surface: inside, and on one of its faces
        assert np.all(moved <= size / 2 + 1e-12)
        assert np.all(np.isclose(moved, size / 2, atol=1e-12).any(axis=1))
        assert _max_nn(box.vertices @ S[:3, :3].T, box.vertices) < 1e-12  # corners onto corners
        assert _max_nn(kp @ S[:3, :3].T, kp) < 1e-12
