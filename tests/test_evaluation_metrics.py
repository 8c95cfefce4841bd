"""Pose error metrics: ADD family (ADD-H exact), symmetry-aware errors, VSD, BOP symmetries."""
from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from dope_hope.evaluation import metrics
from dope_hope.symmetry.transforms import category_symmetries, symmetries_from_models_info

I3 = np.eye(3)
Z3 = np.zeros(3)


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def ring_cylinder(radius=0.035, height=0.1, n_angles=36, n_levels=5) -> np.ndarray:
    """Points on a cylinder about y, on a regular angular grid (rotation-invariant by 10°)."""
    a = np.radians(np.arange(n_angles) * 360.0 / n_angles)
    ys = np.linspace(-height / 2, height / 2, n_levels)
    return np.array([[radius * math.cos(t), y, radius * math.sin(t)] for y in ys for t in a])


def box_points(size=(0.06, 0.1, 0.04), n=400, seed=0) -> np.ndarray:
    return np.asarray(trimesh.sample.sample_surface(trimesh.creation.box(extents=size), n,
                                                    seed=seed)[0])


def brute_force_assignment(a: np.ndarray, b: np.ndarray) -> float:
    return min(np.linalg.norm(a - b[list(p)], axis=1).mean()
               for p in itertools.permutations(range(len(a))))


# ----------------------------------------------------------------------------- ADD family
def test_cylinder_rotated_about_its_axis_meanssd_and_addh_vanish_but_add_does_not():
    pts = ring_cylinder()
    R_g, t_g = rot("x", 20), np.array([0.02, -0.01, 0.7])
    R_e = R_g @ rot("y", 40)  # a multiple of the 10° grid and of the 1° symmetry step
    syms = category_symmetries("cylinder")
    assert metrics.add(R_e, t_g, R_g, t_g, pts) > 0.02
    assert metrics.addh(R_e, t_g, R_g, t_g, pts) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mean_ssd(R_e, t_g, R_g, t_g, pts, syms) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mssd(R_e, t_g, R_g, t_g, pts, syms) == pytest.approx(0.0, abs=1e-12)
    # without the symmetry list MeanSSD is plain ADD
    assert metrics.mean_ssd(R_e, t_g, R_g, t_g, pts, None) == pytest.approx(
        metrics.add(R_e, t_g, R_g, t_g, pts))


def test_addh_is_small_for_the_500_point_sample_of_a_rotated_cylinder():
    from dope_hope.io.meshes import sample_surface_points

    mesh = trimesh.creation.cylinder(radius=0.035, height=0.1, sections=64)
    pts = sample_surface_points(mesh, 500)  # what evaluate uses (farthest-point sample)
    R_e = rot("z", 73)  # trimesh's cylinder axis is z
    add = metrics.add(R_e, Z3, I3, Z3, pts)
    assert add > 0.03
    assert metrics.addh(R_e, Z3, I3, Z3, pts) < 0.005  # about half the point spacing


@settings(max_examples=25, deadline=None)
@given(rv=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
       tv=st.lists(st.floats(-0.1, 0.1), min_size=3, max_size=3),
       n=st.integers(5, 60), seed=st.integers(0, 1000))
def test_adds_le_addh_le_add(rv, tv, n, seed):
    pts = np.random.default_rng(seed).normal(scale=0.03, size=(n, 3))
    R_e = Rotation.from_rotvec(rv).as_matrix()
    t_e = np.array(tv)
    args = (R_e, t_e, rot("y", 10), np.array([0.0, 0.0, 0.5]), pts)
    s, h, a = metrics.adds(*args), metrics.addh(*args), metrics.add(*args)
    assert s <= h + 1e-12
    assert h <= a + 1e-12


@pytest.mark.parametrize("seed", range(40))
def test_addh_equals_brute_force_optimal_assignment(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 7))
    pts = rng.normal(scale=0.05, size=(n, 3))
    R_e = Rotation.random(random_state=seed).as_matrix()
    t_e = rng.normal(scale=0.03, size=3)
    a = pts @ I3.T
    b = pts @ R_e.T + t_e
    assert metrics.addh(R_e, t_e, I3, Z3, pts) == pytest.approx(brute_force_assignment(a, b), abs=1e-12)


def dense_lsa(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    """The HOPE paper's computation: scipy's solver on the full distance matrix."""
    C = cdist(a, b)
    r, c = linear_sum_assignment(C)
    return float(C[r, c].mean()), c


def lattice(spacing=0.01) -> np.ndarray:
    """256 points on an 8 x 8 x 4 grid, centred."""
    g = np.arange(8) * spacing
    pts = np.stack(np.meshgrid(g, g, g[:4], indexing="ij"), -1).reshape(-1, 3)
    return pts - pts.mean(axis=0)


@pytest.fixture
def stages(monkeypatch):
    """Records which solver stages assignment_distance ran: 'sub' (group duals), 'lsa'."""
    calls: list[str] = []
    sub, lsa = metrics._group_potentials, metrics.linear_sum_assignment
    monkeypatch.setattr(metrics, "_group_potentials", lambda *a: calls.append("sub") or sub(*a))
    monkeypatch.setattr(metrics, "linear_sum_assignment", lambda *a: calls.append("lsa") or lsa(*a))
    return calls


@pytest.mark.parametrize("deg,shift,expected_stages", [
    (0, 0.02, []),                      # pure translation: the identity meets the centroid bound
    (2, 0.01, ["lsa"]),                 # near: the solver on the linear-potential reduction
    (30, 0.02, ["sub"] + ["lsa"] * 5),  # hard: 4 sub-problems' duals, then the solver
    (180, 0.3, ["sub"] + ["lsa"] * 5),
])
def test_addh_is_bitwise_the_dense_solvers_value_at_500_points(deg, shift, expected_stages, stages):
    pts = box_points(n=500, seed=1)
    R_e = Rotation.from_rotvec(np.radians(deg) * np.array([0.6, 0.0, 0.8])).as_matrix()
    b = pts @ R_e.T + np.array([shift, -shift / 2, 0.0])
    value, perm = metrics.assignment_distance(pts, b, return_assignment=True)
    assert stages == expected_stages
    expected, c = dense_lsa(pts, b)
    # a unique optimum: the same permutation, so the same float, not just a close one
    assert value == expected
    assert np.array_equal(perm, c)


@pytest.mark.parametrize("shift", [(0.0, 0.0, 0.0), (0.013, 0.007, 0.004)])
def test_addh_certified_by_a_dual_potential_skips_the_solver(shift, stages):
    # points moved by less than their spacing: the row-wise minimisers of C - v (v = 0 when
    # the centroids coincide, else the linear potential) form a permutation: optimal
    a = lattice()
    noise = np.random.default_rng(0).normal(scale=2e-4, size=a.shape)
    b = a + np.array(shift) + (noise - noise.mean(axis=0))
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert stages == []
    expected, c = dense_lsa(a, b)
    assert value == expected
    assert np.array_equal(perm, c)


@pytest.mark.parametrize("n", [160, 161, 163, 250, 333])
def test_addh_group_warm_start_keeps_the_dense_solvers_optimum(n, stages):
    # a far rotation with groups of unequal size (n not a multiple of 4): the interleaved
    # sub-problems' averaged duals only seed the solver; the optimum is the dense one's
    pts = box_points(n=n, seed=n)
    R_e = Rotation.from_rotvec([2.0, -1.0, 0.5]).as_matrix()
    b = pts @ R_e.T + np.array([0.02, 0.0, -0.01])
    value, perm = metrics.assignment_distance(pts, b, return_assignment=True)
    assert stages[0] == "sub"
    expected, c = dense_lsa(pts, b)
    assert value == expected
    assert np.array_equal(perm, c)


def test_addh_group_warm_start_with_ties_has_the_dense_solvers_value(stages):
    # a symmetric lattice turned by 180 deg: many optimal permutations, and the sub-problems
    # (every 4th grid point) are degenerate too
    a = lattice()
    b = a @ rot("y", 180).T + np.array([0.0, 0.004, 0.0])
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert stages[0] == "sub"
    assert sorted(perm) == list(range(len(a)))
    assert cdist(a, b)[np.arange(len(a)), perm].mean() == value
    assert value == pytest.approx(dense_lsa(a, b)[0], abs=1e-12)


def _tie_case(name: str) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    if name == "duplicated points":
        a = np.repeat(box_points(n=250, seed=2), 2, axis=0)
        return a, a @ rot("y", 40).T + np.array([0.01, 0.0, 0.02])
    if name == "lattice onto itself":  # 90 deg about z maps the grid onto itself
        a = lattice()
        return a, a @ rot("z", 90).T
    if name == "lattice, axis shift":  # collinear points: many optimal assignments
        a = lattice()
        return a, a @ rot("x", 180).T + np.array([0.01, 0.0, 0.0])
    if name == "symmetric cylinder":
        a = ring_cylinder()
        return a, a @ rot("y", 45).T + np.array([0.0, 0.003, 0.0])
    if name == "all points coincide":  # every permutation costs the same
        return np.zeros((200, 3)), rng.normal(scale=0.05, size=(200, 3))
    raise ValueError(name)


@pytest.mark.parametrize("name", ["duplicated points", "lattice onto itself", "lattice, axis shift",
                                  "symmetric cylinder", "all points coincide"])
def test_addh_with_ties_has_the_dense_solvers_value(name):
    # several optimal permutations: another one than scipy's may come back; the values are
    # proved equal up to the rounding of the reduced matrix, far below 1e-12 m
    a, b = _tie_case(name)
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert sorted(perm) == list(range(len(a)))
    assert cdist(a, b)[np.arange(len(a)), perm].mean() == value
    assert value == pytest.approx(dense_lsa(a, b)[0], abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 220), seed=st.integers(0, 10_000),
       shift=st.sampled_from([0.0, 0.003, 0.03, 0.3]), rigid=st.booleans())
def test_addh_equals_the_dense_solver_on_random_problems(n, seed, shift, rigid):
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=0.05, size=(n, 3))
    if rigid:  # the same points in another pose, as in ADD-H
        b = a @ Rotation.random(random_state=seed).as_matrix().T
    else:
        b = rng.normal(scale=0.05, size=(n, 3))
    b = b + shift * rng.normal(size=3)
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert sorted(perm) == list(range(n))
    assert value == pytest.approx(dense_lsa(a, b)[0], abs=1e-12)


def test_assignment_is_a_permutation_and_reaches_the_reported_value():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(300, 3))
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert sorted(perm) == list(range(300))
    assert np.linalg.norm(a - b[perm], axis=1).mean() == pytest.approx(value, abs=1e-14)


def test_addh_of_a_pure_translation_is_the_translation_length():
    pts = box_points()
    t = np.array([0.03, -0.04, 0.0])
    assert metrics.addh(I3, t, I3, Z3, pts) == pytest.approx(0.05, abs=1e-12)


@pytest.mark.parametrize("n,scale,seed", [(1, 0.05, 0), (7, 1e-4, 1), (500, 0.05, 2), (500, 30.0, 3)])
def test_addh_of_a_pure_translation_is_bitwise_the_dense_solvers_value(n, scale, seed, stages):
    # the short-cut computes the identity's distances without the distance matrix: they must
    # be the very floats cdist gives, or the mean would differ from the dense solver's
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=scale, size=(n, 3))
    b = a + scale * rng.normal(size=3)
    value, perm = metrics.assignment_distance(a, b, return_assignment=True)
    assert stages == []
    assert np.array_equal(perm, np.arange(n))
    assert value == dense_lsa(a, b)[0]


def test_addh_upper_cutoff_returns_a_bound_at_or_above_the_cutoff():
    pts = box_points(n=200)
    R_e, t_e = rot("x", 90), np.array([0.5, 0.0, 0.0])
    exact = metrics.addh(R_e, t_e, I3, Z3, pts)
    cut = metrics.addh(R_e, t_e, I3, Z3, pts, upper=0.1)
    assert 0.1 <= cut <= exact + 1e-12
    # below the cut-off the exact value is returned
    R_s = rot("x", 5)
    assert metrics.addh(R_s, Z3, I3, Z3, pts, upper=0.1) == pytest.approx(
        metrics.addh(R_s, Z3, I3, Z3, pts))


def test_addh_upper_cutoff_uses_the_dual_bound_when_the_centroids_are_close():
    pts = box_points(n=500, seed=1)
    R_e, t_e = rot("x", 150), np.array([0.01, 0.0, 0.0])
    exact = metrics.addh(R_e, t_e, I3, Z3, pts)
    upper = 0.9 * exact  # far above the 1 cm centroid distance
    value, perm = metrics.assignment_distance(pts, pts @ R_e.T + t_e, upper=upper,
                                              return_assignment=True)
    assert perm is None
    assert upper <= value <= exact + 1e-12


def test_addh_rejects_mismatched_point_sets():
    with pytest.raises(ValueError, match="differ in size"):
        metrics.assignment_distance(np.zeros((3, 3)), np.zeros((4, 3)))


# ----------------------------------------------------------------------------- symmetries
def test_mssd_of_a_box_flipped_by_one_of_its_symmetries_is_zero():
    pts = box_points()
    R_g, t_g = rot("z", 25) @ rot("x", 10), np.array([0.0, 0.05, 0.8])
    R_e = R_g @ rot("y", 180)
    syms = category_symmetries("cuboid")
    assert metrics.mssd(R_e, t_g, R_g, t_g, pts, syms) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mssd(R_e, t_g, R_g, t_g, pts, None) > 0.03


def test_mean_ssd_le_mssd_and_chunking_over_720_symmetries_is_consistent(monkeypatch):
    pts = ring_cylinder()
    syms = category_symmetries("cylinder")  # 720 transforms
    R_e, t_e = rot("x", 7) @ rot("y", 33.4), np.array([0.004, 0.0, 0.002])
    m1 = metrics.mean_ssd(R_e, t_e, I3, Z3, pts, syms)
    x1 = metrics.mssd(R_e, t_e, I3, Z3, pts, syms)
    monkeypatch.setattr(metrics, "_SYM_CHUNK_ELEMENTS", 1)  # one symmetry per chunk
    assert metrics.mean_ssd(R_e, t_e, I3, Z3, pts, syms) == pytest.approx(m1, abs=1e-15)
    brute = min(np.linalg.norm((pts @ S[:3, :3].T + S[:3, 3]) - (pts @ R_e.T + t_e), axis=1).mean()
                for S in syms)
    assert m1 == pytest.approx(brute, abs=1e-14)
    assert m1 <= x1


def test_mspd_scales_with_focal_length():
    pts = box_points()
    R_g, t_g = rot("y", 20), np.array([0.0, 0.0, 0.6])
    R_e, t_e = R_g @ rot("x", 8), t_g + np.array([0.01, 0.0, 0.0])
    K1 = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    K2 = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    e1 = metrics.mspd(R_e, t_e, R_g, t_g, K1, pts, None)
    assert e1 > 1.0
    assert metrics.mspd(R_e, t_e, R_g, t_g, K2, pts, None) == pytest.approx(2 * e1, rel=1e-12)
    syms = category_symmetries("cuboid")
    assert metrics.mspd(R_g @ rot("z", 180), t_g, R_g, t_g, K1, pts, syms) == pytest.approx(0, abs=1e-9)


def test_symmetries_from_models_info_discretizes_like_the_bop_toolkit():
    info = {"symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 20, 0, 0, 0, 1]],
            "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [10, 0, 0]}]}
    S = symmetries_from_models_info(info, max_sym_disc_step=0.01)
    steps = math.ceil(math.pi / 0.01)  # 315
    assert S.shape == (2 * steps, 4, 4)
    np.testing.assert_allclose(S[0], np.eye(4), atol=1e-12)
    for M in S:
        np.testing.assert_allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(M[3], [0, 0, 0, 1])
    # continuous part: rotations about z through the offset (10 mm -> 0.01 m) fix that point
    p = np.array([0.01, 0.0, 0.3])
    for M in S[:steps]:
        np.testing.assert_allclose(M[:3, :3] @ p + M[:3, 3], p, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(S[1, :3, :3]).as_rotvec(),
                               [0, 0, 2 * math.pi / steps], atol=1e-12)
    # discrete part combined: translation in metres (20 mm)
    np.testing.assert_allclose(S[steps, :3, 3], [0, 0, 0.02], atol=1e-12)
    only_discrete = symmetries_from_models_info({"symmetries_discrete": info["symmetries_discrete"]})
    assert only_discrete.shape == (2, 4, 4)
    assert symmetries_from_models_info({}).shape == (1, 4, 4)


def test_bop_units_keep_the_stored_numbers_and_errors_are_exact_on_integer_data():
    """In the file's millimetres (unit=1.0) a discrete symmetry is used as stored (R not
    re-orthonormalized, t = 20 mm); a 15 mm shift gives MSSD 15.0 and, at depth 1000 with
    f = 1000, MSPD 15.0 px, exactly: the ties the BOP thresholds are compared with."""
    R_s = [1.0000001, 0, 0, 0, -1, 0, 0, 0, -1]
    info = {"symmetries_discrete": [R_s[0:3] + [0] + R_s[3:6] + [0] + R_s[6:9] + [20, 0, 0, 0, 1]]}
    S = symmetries_from_models_info(info, unit=1.0)
    np.testing.assert_array_equal(S[1, :3, :3].ravel(), R_s)
    assert S[1, 2, 3] == 20.0
    square = np.array([[-50.0, -50, 0], [50, -50, 0], [-50, 50, 0], [50, 50, 0]])
    t_g = np.array([0.0, 0.0, 1000.0])
    assert metrics.mssd(I3, t_g + [15, 0, 0], I3, t_g, square, None) == 15.0
    K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
    assert metrics.mspd(I3, t_g + [15, 0, 0], I3, t_g, K, square, None) == 15.0


def test_symmetries_of_the_shared_cylinder_model_make_axis_rotations_nearly_free(shared_data):
    info = json.loads((shared_data / "symmetric_models" / "cylinder" / "model_info.json").read_text())
    syms = symmetries_from_models_info(info)
    mesh = trimesh.load(str(shared_data / "symmetric_models" / "cylinder" / "textured.obj"), force="mesh")
    pts = np.asarray(mesh.vertices)
    pts = pts - (pts.max(0) + pts.min(0)) / 2
    radius = np.linalg.norm(pts[:, :2], axis=1).max()
    R_e = rot("z", 47.3) @ rot("x", 180)
    assert metrics.mssd(R_e, Z3, I3, Z3, pts, syms) <= radius * (math.pi / 315) + 1e-9
    assert metrics.mssd(R_e, Z3, I3, Z3, pts, None) > radius


def test_te_and_re():
    assert metrics.te([0, 0, 1], [0, 3, 5]) == pytest.approx(5.0)
    assert metrics.re(rot("x", 30), I3) == pytest.approx(30.0)
    assert metrics.re(rot("y", 180), I3) == pytest.approx(180.0)


# ----------------------------------------------------------------------------- VSD
@pytest.fixture(scope="module")
def renderer():
    from dope_hope.render.depth import DepthRenderer

    r = DepthRenderer()
    yield r
    r.close()


K_VSD = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])


def box_model(size_mm: float = 80.0):
    box = trimesh.creation.box(extents=(size_mm,) * 3)
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces)


def test_depth_renderer_samples_pixel_centres_at_half_integers_as_the_toolkit(renderer):
    """The toolkit's renderer puts pixel column i at u = i + 0.5 of K (OpenGL pixel centres)
    and its depth is exact on a fronto-parallel face (near plane at the box's front)."""
    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    depth = renderer.render_depth(box_model(100.0), I3, np.array([0.0, 0.0, 1000.0]), K, 640, 480)
    ys, xs = np.nonzero(depth)
    # front face at z = 950: u in 320 +- 1000 * 50 / 950 = [267.37, 372.63] -> columns whose
    # centre i + 0.5 is inside: 267 .. 372 (with centres at integers it would be 268 .. 372)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (267, 372, 187, 292)
    assert depth.dtype == np.float64 and np.all(depth[ys, xs] == 950.0)
    assert np.count_nonzero(depth) == 106 * 106


def test_depth_to_distance_is_the_toolkits_formula():
    K = np.array([[500.0, 0, 2.0], [0, 400.0, 1.0], [0, 0, 1]])
    depth = np.full((3, 5), 800.0, np.float32)
    depth[0, 0] = 0.0
    d = metrics.depth_to_distance(depth, K)
    y, x = 2, 4
    assert d[y, x] == math.sqrt((((x - 2.0) / 500.0) * 800.0) ** 2 + (((y - 1.0) / 400.0) * 800.0) ** 2
                                + 800.0 ** 2)
    assert d[1, 2] == 800.0 and d[0, 0] == 0.0


class PlaneRenderer:
    """A stand-in renderer: a 1x1 image whose pixel (at the principal point, so distance =
    depth exactly) shows depth ``z[t]`` for a pose with translation ``t``."""

    def __init__(self, z: dict):
        self.z = z

    def render_depth(self, model, R, t, K, width, height):
        return np.full((height, width), self.z[tuple(np.asarray(t, float).ravel())], np.float64)


K_1PX = np.array([[1000.0, 0, 0.0], [0, 1000.0, 0.0], [0, 0, 1]])
T_G, T_E = (0.0, 0.0, 1000.0), (0.0, 0.0, 1015.0)


def test_vsd_step_cost_ties_at_tau_follow_the_toolkits_thresholds():
    """|1015 - 1000| / 100 = 0.15 exactly: a cost at tau 0.05 and 0.1 (dists >= tau) but not
    at the toolkit's third tau 0.15000000000000002 (np.arange); with a tau of 0.15 it would be."""
    r = PlaneRenderer({T_G: 1000.0, T_E: 1015.0})
    depth = np.full((1, 1), 1000.0, np.float32)
    e = metrics.vsd(I3, np.array(T_E), I3, np.array(T_G), depth, K_1PX, None, delta=15.0,
                    diameter=100.0, renderer=r)
    assert e == [1.0, 1.0] + [0.0] * 8
    assert metrics.BOP19_VSD_TAUS[2] == 0.15000000000000002
    e_rounded = metrics.vsd(I3, np.array(T_E), I3, np.array(T_G), depth, K_1PX, None, delta=15.0,
                            diameter=100.0, taus=[0.15], renderer=r)
    assert e_rounded == [1.0]


@pytest.mark.parametrize("test_depth,expected", [(985.0, 0.0), (984.9, 1.0), (0.0, 0.0)])
def test_vsd_visibility_tolerance_is_inclusive_and_missing_depth_is_visible(test_depth, expected):
    """GT surface 15 mm behind the test surface is still visible (d_diff <= delta); 15.1 mm is
    not, and then nothing is visible: VSD = 1; no test depth counts as visible."""
    r = PlaneRenderer({T_G: 1000.0})
    depth = np.full((1, 1), test_depth, np.float32)
    e = metrics.vsd(I3, np.array(T_G), I3, np.array(T_G), depth, K_1PX, None, delta=15.0,
                    diameter=100.0, renderer=r)
    assert e == [expected] * 10


def test_vsd_is_zero_for_identical_poses_and_one_for_disjoint_ones(renderer):
    model = box_model()
    t_g = np.array([0.0, 0.0, 600.0])
    depth = renderer.render_depth(model, I3, t_g, K_VSD, 160, 120).astype(np.float32)
    kw = dict(delta=15.0, diameter=float(np.linalg.norm([80.0] * 3)), renderer=renderer)
    assert metrics.vsd(I3, t_g, I3, t_g, depth, K_VSD, model, **kw) == [0.0] * 10
    assert metrics.vsd(I3, t_g + [300.0, 0, 0], I3, t_g, depth, K_VSD, model, **kw) == [1.0] * 10
    assert metrics.vsd(I3, t_g, I3, t_g, np.zeros_like(depth), K_VSD, model, **kw) == [0.0] * 10


def test_vsd_depth_offset_is_forgiven_only_by_tolerances_above_it(renderer):
    model = box_model()
    diameter = float(np.linalg.norm([80.0] * 3))
    t_g = np.array([0.0, 0.0, 600.0])
    depth = renderer.render_depth(model, I3, t_g, K_VSD, 160, 120).astype(np.float32)
    shift = 10.0  # behind: within delta (15 mm), so the estimate stays "visible"
    e = np.array(metrics.vsd(I3, t_g + [0, 0, shift], I3, t_g, depth, K_VSD, model, delta=15.0,
                             diameter=diameter, renderer=renderer))
    taus = np.array(metrics.BOP19_VSD_TAUS)
    assert np.all(e[taus * diameter > shift * 1.02] < 0.2)
    assert np.all(e[taus * diameter < shift * 0.98] > 0.8)
    assert np.all(np.diff(e) <= 1e-12)


def test_vsd_tlinear_cost_and_bad_cost_type(renderer):
    model = box_model()
    t_g = np.array([0.0, 0.0, 600.0])
    depth = renderer.render_depth(model, I3, t_g, K_VSD, 160, 120).astype(np.float32)
    kw = dict(delta=15.0, diameter=138.6, renderer=renderer)
    e = metrics.vsd(I3, t_g + [0, 0, 5.0], I3, t_g, depth, K_VSD, model, cost_type="tlinear", **kw)
    assert 0 < e[-1] < e[0] < 1
    with pytest.raises(ValueError, match="cost type"):
        metrics.vsd(I3, t_g, I3, t_g, depth, K_VSD, model, cost_type="nope", **kw)


def test_sphere_projections_overlap():
    assert metrics.sphere_projections_overlap(0.05, [0, 0, 1], [0.05, 0, 1])
    assert not metrics.sphere_projections_overlap(0.05, [0, 0, 1], [0.2, 0, 1])
    assert not metrics.sphere_projections_overlap(0.05, [0, 0, 0], [0, 0, 1])
