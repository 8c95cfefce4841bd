"""dope_hope.io.meshes: units, textures, errors, surface sampling, cuboid and diameter."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dope_hope.catalog import get_object
from dope_hope.errors import DopeHopeError, InputFileError
from dope_hope.io.meshes import (
    UNIT_SCALE,
    load_mesh,
    mesh_cuboid,
    mesh_diameter,
    read_ply,
    sample_surface_points,
)


@pytest.fixture(scope="module")
def ketchup(ketchup_obj):
    return load_mesh(ketchup_obj)


def test_ketchup_obj_loads_in_metres_with_texture(ketchup):
    size, center = mesh_cuboid(ketchup)
    # shared/data README: extents x 6.45, y 14.86, z 4.34 cm
    np.testing.assert_allclose(size, [0.0645, 0.1486, 0.0434], atol=2e-4)
    np.testing.assert_allclose(center, 0.0, atol=1e-4)  # HOPE meshes are box-centred
    assert isinstance(ketchup.visual, trimesh.visual.TextureVisuals)
    assert ketchup.visual.uv.shape == (len(ketchup.vertices), 2)
    assert ketchup.visual.material.image.size == (2048, 2048)


def test_units_override_and_ply_default_mm(tmp_path, ketchup_obj):
    in_m = load_mesh(ketchup_obj, units="m", check_size=False)  # a 15 m bottle: see the next test
    in_cm = load_mesh(ketchup_obj)
    np.testing.assert_allclose(in_m.extents, in_cm.extents * 100.0, rtol=1e-9)
    box = trimesh.creation.box(extents=[10.0, 20.0, 30.0])  # "millimetres"
    box.export(tmp_path / "box.ply")
    np.testing.assert_allclose(load_mesh(tmp_path / "box.ply").extents, [0.01, 0.02, 0.03])
    np.testing.assert_allclose(load_mesh(tmp_path / "box.ply", units="cm").extents, [0.1, 0.2, 0.3])


@pytest.mark.parametrize("extents, units, likely, what", [
    ([0.05, 0.05, 0.08], "cm", "m", "too small for an object (largest side under 5 mm)"),  # metres read as cm
    ([0.05, 0.05, 0.08], "mm", "m", "too small"),
    ([50.0, 50.0, 80.0], "m", "mm", "too large for an object (largest side over 5 m)"),  # mm read as m
    ([6.45, 14.86, 4.34], "m", "cm", "too large"),  # the HOPE Ketchup (cm) read as metres
    ([1e-6, 1e-6, 1e-6], "m", None, "too small"),
])
def test_a_mesh_implausible_in_its_unit_is_refused_with_the_likely_unit(tmp_path, extents, units, likely, what):
    path = tmp_path / "object.obj"
    trimesh.creation.box(extents=extents).export(path)
    with pytest.raises(InputFileError) as err:
        load_mesh(path, units=units)
    message = str(err.value)
    assert message.startswith(f"{path}: mesh box ") and f"(read in {units}) is {what}" in message
    if likely is None:
        assert "no unit (m, cm, mm) makes it an object's size" in message
    else:
        assert message.endswith(f"the file is likely in {likely}: give its unit as {likely}")
        assert load_mesh(path, units=likely).extents.max() == pytest.approx(0.08 if likely == "m" else
                                                                           0.08 if likely == "mm" else 0.1486)
    for unit in ("m", "cm", "mm"):  # the bounds: 5 mm and 5 m are plausible
        edge = tmp_path / f"edge_{unit}.obj"
        trimesh.creation.box(extents=[0.005 / UNIT_SCALE[unit]] * 3).export(edge)
        assert load_mesh(edge, units=unit).extents.max() == pytest.approx(0.005)


def test_multi_part_obj_is_one_mesh(tmp_path):
    a = trimesh.creation.box(extents=[1, 1, 1])
    b = trimesh.creation.box(extents=[1, 1, 1])
    b.apply_translation([3, 0, 0])
    trimesh.Scene({"a": a, "b": b}).export(tmp_path / "two.obj")
    mesh = load_mesh(tmp_path / "two.obj")  # cm
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.faces) == 24
    np.testing.assert_allclose(mesh.extents, [0.04, 0.01, 0.01], atol=1e-9)


@pytest.mark.parametrize("content", [None, b"", b"this is not a mesh\n\x00\x01", b"v 1 2 3\n"])
def test_missing_or_corrupt_mesh_names_the_file(tmp_path, content):
    path = tmp_path / "broken.obj"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputFileError) as err:
        load_mesh(path)
    assert str(path) in str(err.value)
    assert isinstance(err.value, DopeHopeError)


def test_unknown_unit_is_an_input_error(ketchup_obj):
    with pytest.raises(InputFileError, match="unit"):
        load_mesh(ketchup_obj, units="inch")


def test_sample_surface_points_deterministic_on_surface_and_spread(ketchup):
    pts = sample_surface_points(ketchup, 500, seed=0)
    assert pts.shape == (500, 3)
    np.testing.assert_array_equal(pts, sample_surface_points(ketchup, 500, seed=0))
    assert not np.array_equal(pts, sample_surface_points(ketchup, 500, seed=1))
    # a subset of the dense area-weighted surface sample (10000 points for n = 500), each
    # point inside its triangle's plane
    dense, faces = trimesh.sample.sample_surface(ketchup, 10000, seed=0)
    dist, idx = cKDTree(dense).query(pts)
    assert dist.max() == 0.0
    tri = ketchup.triangles[faces[idx]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", pts - tri[:, 0], normal)).max() < 1e-9
    # farthest-point spread: the nearest-neighbour gap is far more uniform than for a
    # random subset of the same size
    rand = trimesh.sample.sample_surface(ketchup, 500, seed=0)[0]
    nn_fps = cKDTree(pts).query(pts, k=2)[0][:, 1]
    nn_rand = cKDTree(rand).query(rand, k=2)[0][:, 1]
    assert nn_fps.min() > 3 * nn_rand.min()
    assert nn_fps.std() / nn_fps.mean() < nn_rand.std() / nn_rand.mean()
    # and covers the whole bottle: the sample's box is the mesh's box within a few mm
    np.testing.assert_allclose(pts.min(0), ketchup.bounds[0], atol=4e-3)
    np.testing.assert_allclose(pts.max(0), ketchup.bounds[1], atol=4e-3)


def test_mesh_diameter_matches_brute_force_and_box():
    box = trimesh.creation.box(extents=[0.03, 0.04, 0.12])
    assert mesh_diameter(box) == pytest.approx(0.13, abs=1e-12)
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(300, 3))
    brute = np.max(np.linalg.norm(pts[:, None] - pts[None], axis=-1))
    assert mesh_diameter(pts) == pytest.approx(brute, rel=1e-12)
    # degenerate (flat) point set still works
    flat = np.c_[rng.normal(size=(50, 2)), np.zeros(50)]
    brute = np.max(np.linalg.norm(flat[:, None] - flat[None], axis=-1))
    assert mesh_diameter(flat) == pytest.approx(brute, rel=1e-12)


def test_ketchup_mesh_matches_catalog_and_y_is_vertical(ketchup):
    size, _ = mesh_cuboid(ketchup)
    np.testing.assert_allclose(size, get_object("Ketchup").size_array, atol=5e-4)
    assert int(np.argmax(size)) == 1  # y: the bottle's vertical axis is its longest
    d = mesh_diameter(ketchup)
    assert size.max() < d <= np.linalg.norm(size)


def test_texture_reaches_pyrender(ketchup):
    """The loaded visuals are what pyrender needs to texture the mesh (no GL context used)."""
    from dope_hope.render.gl import import_pyrender

    pyrender = import_pyrender()
    prim = pyrender.Mesh.from_trimesh(ketchup).primitives[0]
    assert prim.material.baseColorTexture is not None
    assert prim.texcoord_0.shape == (len(ketchup.vertices), 2)
    np.testing.assert_allclose(prim.positions.max(0), ketchup.bounds[1], atol=1e-6)  # metres


PLY_HEADER = "ply\nformat {fmt} 1.0\ncomment a point cloud: no faces\nelement vertex {n}\n" \
             "property float x\nproperty float y\nproperty double z\nproperty uchar red\n" \
             "end_header\n"


def test_read_ply_vertices_ascii_keeps_text_precision_order_and_duplicates(tmp_path):
    """Every vertex as the BOP toolkit's load_ply reads it: ascii parsed as float64 (0.1 is
    the double 0.1, not the float32 0.1 that trimesh gives), duplicates and order kept, no
    faces needed, file units (no scaling)."""
    rows = ["0.1 -12.345678 1000.0000001 7", "0.1 -12.345678 1000.0000001 7", "3 2 1 0"]
    path = tmp_path / "cloud.ply"
    path.write_text(PLY_HEADER.format(fmt="ascii", n=3) + "\n".join(rows) + "\n")
    v, faces = read_ply(path)
    assert v.dtype == np.float64 and faces is None
    np.testing.assert_array_equal(v, [[0.1, -12.345678, 1000.0000001]] * 2 + [[3.0, 2.0, 1.0]])


@pytest.mark.parametrize("fmt,order", [("binary_little_endian", "<"), ("binary_big_endian", ">")])
def test_read_ply_vertices_binary_widens_the_stored_values_exactly(tmp_path, fmt, order):
    dtype = np.dtype([("x", order + "f4"), ("y", order + "f4"), ("z", order + "f8"), ("r", "u1")])
    rec = np.array([(0.1, 2.5, 0.1, 9), (-7.25, 1e-3, 1e6, 0)], dtype=dtype)
    path = tmp_path / "m.ply"
    path.write_bytes(PLY_HEADER.format(fmt=fmt, n=2).encode() + rec.tobytes())
    v, _ = read_ply(path)
    np.testing.assert_array_equal(v[:, 0], np.array([0.1, -7.25], np.float32).astype(np.float64))
    np.testing.assert_array_equal(v[:, 1], np.array([2.5, 1e-3], np.float32).astype(np.float64))
    np.testing.assert_array_equal(v[:, 2], [0.1, 1e6])


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_read_ply_of_a_mesh_gives_its_file_vertices_and_triangles(tmp_path, encoding):
    box = trimesh.creation.box(extents=[10.0, 20.0, 30.0])
    (tmp_path / "box.ply").write_bytes(trimesh.exchange.ply.export_ply(box, encoding=encoding))
    v, faces = read_ply(tmp_path / "box.ply")
    np.testing.assert_array_equal(v, np.asarray(box.vertices, np.float32).astype(np.float64))
    np.testing.assert_array_equal(faces, box.faces)


@pytest.mark.parametrize("content,problem", [
    (None, "not found"), (b"solid stl\n", "not a PLY"),
    (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
     b"element vertex 1\nproperty float x\nend_header\n", "first element must be 'vertex'"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
     b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
     b"0 0 0\n1 0 0\n0 1 0\n4 0 1 2 0\n", "only triangular faces"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n1 2 3\n", "expected 2 vertex lines"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
     b"property float y\nproperty float z\nend_header\n" + bytes(12), "ends before its 2 vertices"),
])
def test_read_ply_vertices_bad_files_name_the_file(tmp_path, content, problem):
    path = tmp_path / "bad.ply"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputFileError, match=problem) as err:
        read_ply(path)
    assert str(path) in str(err.value)


def test_read_ply_reads_triangles_past_texcoord_lists(tmp_path):
    """BOP models with per-face texture coordinates (a second face list), binary."""
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
            b"property float y\nproperty float z\nelement face 2\n"
            b"property list uchar int vertex_indices\nproperty list uchar float texcoord\nend_header\n")
    fdtype = np.dtype([("n", "u1"), ("i", "<i4", (3,)), ("m", "u1"), ("t", "<f4", (6,))])
    faces = np.array([(3, (0, 1, 2), 6, (0.5,) * 6), (3, (2, 1, 0), 6, (1.0,) * 6)], dtype=fdtype)
    path = tmp_path / "tex.ply"
    path.write_bytes(head + np.arange(9, dtype="<f4").tobytes() + faces.tobytes())
    v, f = read_ply(path)
    np.testing.assert_array_equal(v, np.arange(9.0).reshape(3, 3))
    np.testing.assert_array_equal(f, [[0, 1, 2], [2, 1, 0]])
