"""The appearance check: the textured mesh rendered at a candidate's equivalent poses against
the image. It must rank the true object above a look-alike of the same shape with another
texture, and pick the true one of the cuboid's symmetric-equivalent poses."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from dope_hope.demo_object import demo_object_mesh
from dope_hope.errors import ConfigError
from dope_hope.inference.appearance import (
    AppearanceCheck,
    AppearanceSettings,
    appearance_similarity,
    candidate_rotations,
    feature_similarity,
    surface_appearance,
)
from dope_hope.render.textured import TexturedRenderer
from dope_hope.symmetry.cuboid import cuboid_rotations, describe_rotation

K = np.array([[220.0, 0.0, 79.5], [0.0, 220.0, 59.5], [0.0, 0.0, 1.0]])
W, H = 160, 120
R_TRUE = Rotation.from_euler("xyz", [15, 30, 5], degrees=True).as_matrix()
T_TRUE = np.array([-0.11, 0.0, 0.75])
R_LOOK = Rotation.from_euler("xyz", [-10, -25, 0], degrees=True).as_matrix()
T_LOOK = np.array([0.11, 0.0, 0.75])


def _texture(mesh) -> np.ndarray:
    material = mesh.visual.material
    image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    return np.asarray(image.convert("RGB"))


def look_alike(mesh):
    """The same box with another texture: the atlas mirrored and its colours swapped."""
    other = mesh.copy()
    img = _texture(mesh)[:, ::-1, [2, 0, 1]]
    material = other.visual.material
    if hasattr(material, "image"):
        material.image = Image.fromarray(np.ascontiguousarray(img))
    else:
        material.baseColorTexture = Image.fromarray(np.ascontiguousarray(img))
    return other


@pytest.fixture(scope="module")
def scene():
    """(image, mesh): the demo box and its look-alike side by side under other lighting."""
    mesh = demo_object_mesh()
    rng = np.random.default_rng(3)
    image = rng.integers(60, 200, size=(H, W, 3)).astype(np.float64)
    for obj, R, t in ((mesh, R_TRUE, T_TRUE), (look_alike(mesh), R_LOOK, T_LOOK)):
        with TexturedRenderer(obj, W, H) as r:
            colour, mask = r.render(R, t, K)
        image[mask] = colour[mask]
    image = 0.8 * image + 15.0 + rng.normal(0.0, 3.0, image.shape)  # gain, offset, noise
    return np.clip(image, 0, 255).astype(np.uint8), mesh


def test_the_true_object_outranks_its_look_alike(scene):
    image, mesh = scene
    check = AppearanceCheck(mesh, cuboid_rotations(np.ptp(mesh.vertices, axis=0)), np.zeros(3))
    try:
        true = check.compare(image, K, R_TRUE, T_TRUE)
        look = check.compare(image, K, R_LOOK, T_LOOK)
    finally:
        check.close()
    assert true.score > 0.8
    assert true.score > look.score + 0.25


def test_the_texture_picks_the_true_equivalent_pose(scene):
    image, mesh = scene
    rotations = cuboid_rotations(np.ptp(mesh.vertices, axis=0))
    check = AppearanceCheck(mesh, rotations, np.zeros(3))
    try:
        for k, S in enumerate(rotations):  # a detector reporting R S^T for each symmetry S
            res = check.compare(image, K, R_TRUE @ S.T, T_TRUE)
            np.testing.assert_allclose(res.R, R_TRUE, atol=1e-9)
            assert res.best == k, describe_rotation(S)
            assert res.ambiguous == ()  # the demo box's faces all differ: nothing left open
    finally:
        check.close()


@pytest.fixture(scope="module")
def start_features():
    """The shipped start's first layers (what MeshStartPredictor gives its check)."""
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.inference.backends import start_backend

    return start_backend(PRETRAINED_WEIGHTS, "Box", np.array([0.1, 0.1, 0.1])).texture_features


def test_feature_similarity_is_the_mean_cosine_inside_the_silhouette():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(8, 4, 4))
    whole = np.ones((16, 16), bool)
    assert feature_similarity(a, 3.0 * a, whole) == pytest.approx(1.0)  # the length does not count
    b = a.copy()
    b[:, :, :2] *= -1.0  # the cells of the two left columns opposite
    assert feature_similarity(a, b, whole) == pytest.approx(0.0, abs=1e-12)
    left = np.zeros((16, 16), bool)
    left[:, :9] = True  # after the one-pixel erosion, the cells of columns 0-1 alone are whole
    assert feature_similarity(a, b, left) == pytest.approx(-1.0)
    corner = np.zeros((16, 16), bool)
    corner[:6, :6] = True  # one whole cell: too few to judge
    assert feature_similarity(a, a, corner) == 0.0


def test_the_starts_first_layers_choose_the_pose_and_the_colour_score_the_object(scene, start_features):
    """With the network's features the chosen pose is theirs (the true one, from a pose turned
    60° about the up axis and from each equivalent pose); how much the object looks like the
    mesh stays the colour score's best; ``texture_features: false`` gives the choice back to the
    colour score."""
    image, mesh = scene
    up = np.array([0.0, 1.0, 0.0])
    turn = Rotation.from_rotvec(np.radians(60.0) * up).as_matrix()
    rotations = cuboid_rotations(np.ptp(mesh.vertices, axis=0))
    check = AppearanceCheck(mesh, rotations, np.zeros(3), AppearanceSettings(spin_step_deg=30.0), up=up,
                            features=start_features)
    plain = AppearanceCheck(mesh, rotations, np.zeros(3), AppearanceSettings(spin_step_deg=30.0, texture_features=False),
                            up=up, features=start_features)
    try:
        assert check.features is not None and plain.features is None
        res = check.compare(image, K, R_TRUE @ turn.T, T_TRUE)
        for k, S in enumerate(rotations):
            each = check.compare(image, K, R_TRUE @ S.T, T_TRUE, turns=False)
            assert each.best == k and len(each.pose_scores) == len(rotations)
        colour = plain.compare(image, K, R_TRUE @ turn.T, T_TRUE)
        look = check.compare(image, K, R_LOOK, T_LOOK)
    finally:
        check.close()
        plain.close()
    np.testing.assert_allclose(res.R, R_TRUE, atol=1e-9)
    assert res.pose_scores[res.best] > 0.8 and np.sort(res.pose_scores)[-2] < res.pose_scores[res.best] - 0.03
    assert res.score == res.scores.max() > 0.8  # the object check: the colour score, as without features
    np.testing.assert_array_equal(colour.pose_scores, colour.scores)
    np.testing.assert_allclose(colour.R, R_TRUE, atol=1e-9)
    assert res.score > look.score + 0.25  # the look-alike is still told by its colours


def test_candidate_rotations_are_the_symmetries_then_the_turns():
    size = np.array([0.06, 0.15, 0.04])
    sym = cuboid_rotations(size)
    np.testing.assert_array_equal(candidate_rotations(sym, np.array([0.0, 1.0, 0.0]), 0.0), sym)
    np.testing.assert_array_equal(candidate_rotations(sym, None, 30.0), sym)
    rots = candidate_rotations(sym, np.array([0.0, 1.0, 0.0]), 30.0)
    np.testing.assert_array_equal(rots[: len(sym)], sym)  # the symmetries first, identity first
    assert len(rots) == 24  # 12 turns upright, 12 upside down; the box's half turns are among them
    np.testing.assert_allclose(rots @ rots.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rots.shape), atol=1e-12)
    assert min(np.linalg.norm(a - b) for i, a in enumerate(rots) for b in rots[:i]) > 0.1  # all distinct
    up = np.array([0.0, 0.0, 1.0])
    turned = candidate_rotations(sym[:1], up, 90.0)
    assert len(turned) == 8 and np.allclose(np.abs((turned @ up) @ up), 1.0)  # the up axis stays an axis
    assert np.sum((turned @ up) @ up < 0) == 4  # four of them upside down


def test_the_texture_turns_the_pose_about_the_up_axis(scene):
    """A detector that knows the box's up axis but not its turn about it (the start on a
    bottle it never saw): the turns find the true pose; the symmetries alone cannot."""
    image, mesh = scene
    up = np.array([0.0, 1.0, 0.0])
    turn = Rotation.from_rotvec(np.radians(60.0) * up).as_matrix()
    check = AppearanceCheck(mesh, cuboid_rotations(np.ptp(mesh.vertices, axis=0)), np.zeros(3),
                            AppearanceSettings(spin_step_deg=30.0), up=up)
    try:
        res = check.compare(image, K, R_TRUE @ turn.T, T_TRUE)
        fixed = check.compare(image, K, R_TRUE @ turn.T, T_TRUE, turns=False)
    finally:
        check.close()
    np.testing.assert_allclose(res.R, R_TRUE, atol=1e-9)
    np.testing.assert_allclose(res.t, T_TRUE, atol=1e-9)  # turned about the centre (here the origin)
    assert res.best >= check.n_symmetries and len(res.scores) == len(check.rotations) == 24
    assert len(fixed.scores) == check.n_symmetries and res.score > fixed.score + 0.2


def test_similarity_follows_the_pattern_more_than_the_lighting():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 255, (32, 32, 3)).astype(np.uint8)
    mask = np.ones((32, 32), bool)
    darker = np.clip(0.7 * a, 0, 255).astype(np.uint8)  # gain: both parts unchanged
    assert appearance_similarity(darker, a, mask, 8) > 0.98
    lifted = np.clip(0.7 * a + 40, 0, 255).astype(np.uint8)  # an offset moves the chromaticity only
    assert appearance_similarity(lifted, a, mask, 8) > 0.75
    assert appearance_similarity(a[::-1], a, mask, 8) < 0.6


def _one_colour(mesh, rgb):
    """``mesh``'s shape in one colour (vertex colours)."""
    import trimesh

    plain = trimesh.Trimesh(mesh.vertices.copy(), mesh.faces.copy(), process=False)
    plain.visual.vertex_colors = [*rgb, 255]
    return plain


def test_surface_appearance_tells_a_texture_from_one_colour_and_from_none(scene):
    import trimesh

    _, mesh = scene
    assert surface_appearance(mesh) == "textured"
    box = trimesh.creation.box(extents=[0.06, 0.15, 0.04])
    assert surface_appearance(box) == "none"  # trimesh's default grey: no colours given
    assert surface_appearance(_one_colour(box, (200, 30, 30))) == "uniform"
    varied = box.copy()
    varied.visual.face_colors = [[200, 30, 30, 255]] * 6 + [[30, 30, 200, 255]] * 6
    assert surface_appearance(varied) == "textured"
    flat = mesh.copy()
    flat.visual.material.image = Image.new("RGB", (64, 64), (90, 140, 40))  # a texture of one colour
    assert surface_appearance(flat) == "uniform"


def test_a_mesh_of_one_colour_tells_look_alikes_by_colour_and_no_pose(scene):
    """One colour cannot tell one pose of the box from another: the check compares the
    candidate's own pose alone, by colour; a box of another colour scores lower. A mesh with no
    colours at all has nothing to compare: refused."""
    import trimesh

    _, mesh = scene
    red = _one_colour(mesh, (200, 40, 30))
    rng = np.random.default_rng(5)
    image = rng.integers(60, 200, size=(H, W, 3)).astype(np.float64)
    with TexturedRenderer(red, W, H) as r:
        colour, mask = r.render(R_TRUE, T_TRUE, K)
    shading = np.linspace(0.6, 1.0, W)[None, :, None]  # light falling off across the object
    image[mask] = (colour * shading)[mask]
    image = np.clip(image + rng.normal(0.0, 3.0, image.shape), 0, 255).astype(np.uint8)
    rotations = cuboid_rotations(np.ptp(mesh.vertices, axis=0))
    checks = [AppearanceCheck(m, rotations, np.zeros(3), AppearanceSettings(spin_step_deg=30.0),
                              up=np.array([0.0, 1.0, 0.0])) for m in (red, _one_colour(mesh, (30, 90, 220)))]
    try:
        same, other = (c.compare(image, K, R_TRUE, T_TRUE) for c in checks)
        assert checks[0].surface == "uniform" and len(checks[0].rotations) == 1 and checks[0].n_symmetries == 1
    finally:
        for c in checks:
            c.close()
    assert len(same.scores) == 1 and same.best == 0 and same.ambiguous == ()
    np.testing.assert_allclose(same.R, R_TRUE)
    assert same.score > 0.6 and same.score > other.score + 0.5, (same.score, other.score)
    with pytest.raises(ConfigError, match="texture or colours"):
        AppearanceCheck(trimesh.creation.box(extents=[0.06, 0.15, 0.04]), rotations[:1], np.zeros(3))


def test_similarity_of_one_colour_is_the_colour_alone():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 255, (32, 32, 3)).astype(np.uint8)
    mask = np.ones((32, 32), bool)
    assert appearance_similarity(a, a, mask, 8) == pytest.approx(1.0)
    flat = np.full_like(a, 128)
    with_texture, colour_only = (appearance_similarity(a, flat, mask, 8, texture=t) for t in (True, False))
    assert colour_only == pytest.approx(2.0 * with_texture)  # no correlation with a flat render: half of it
