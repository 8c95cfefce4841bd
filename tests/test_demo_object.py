"""The embedded demo box: size, texture that fixes the rotation, OBJ export in centimetres."""
import numpy as np
import trimesh

from dope_hope.demo_object import (
    DEMO_SIZE_M,
    demo_object_mesh,
    demo_symmetries,
    demo_texture,
    write_demo_object,
)
from dope_hope.io.symmetries import model_info_declaration
from dope_hope.symmetry.transforms import category_symmetries, declaration_transforms


def test_mesh_is_a_centred_box_of_the_stated_size():
    mesh = demo_object_mesh()
    np.testing.assert_allclose(mesh.extents, DEMO_SIZE_M, atol=1e-9)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    assert mesh.volume > 0  # outward-facing triangles


def test_every_face_looks_different_so_the_label_fixes_the_rotation():
    atlas = demo_texture().astype(np.float64)
    t = atlas.shape[0] // 2
    tiles = [atlas[r * t:(r + 1) * t, c * t:(c + 1) * t] for r in range(2) for c in range(3)]
    for i in range(6):
        for j in range(i + 1, 6):
            assert np.abs(tiles[i] - tiles[j]).mean() > 20, (i, j)
        # no tile is invariant under the 180-degree in-plane turn a box flip would produce
        assert np.abs(tiles[i] - np.rot90(tiles[i], 2)).mean() > 5, i


def test_geometry_is_invariant_under_the_declared_symmetries():
    """The declaration is the cuboid category's group (identity and the three flips)."""
    declared = declaration_transforms(demo_symmetries())
    np.testing.assert_allclose(declared, category_symmetries("cuboid"), atol=1e-12)
    verts = demo_object_mesh().vertices
    for T in declared:
        moved = verts @ T[:3, :3].T + T[:3, 3]
        d = np.min(np.linalg.norm(moved[:, None] - verts[None], axis=2), axis=1)
        assert d.max() < 1e-9


def test_written_obj_is_in_centimetres_with_its_texture(tmp_path):
    path = write_demo_object(tmp_path)
    loaded = trimesh.load(path, force="mesh")
    np.testing.assert_allclose(loaded.extents, DEMO_SIZE_M * 100.0, atol=1e-4)
    assert isinstance(loaded.visual, trimesh.visual.TextureVisuals)
    assert loaded.visual.uv.shape == (24, 2)
    # the declaration beside it is what every command reads for the box
    found = model_info_declaration(path)
    assert found.source == str(tmp_path / "model_info.json")
    np.testing.assert_allclose(declaration_transforms(found), declaration_transforms(demo_symmetries()))
