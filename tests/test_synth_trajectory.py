"""A camera moving through one static scene (dope_hope.synth.trajectory): the first view is the
generator's own frame, the scene turns about the target's centre from view to view, and every
view's annotation is its pose's."""
from __future__ import annotations

import numpy as np
import pytest

from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object
from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.synth.trajectory import orbit_poses


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    import dope_hope.model  # noqa: F401 - torchvision before the GL context
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.trajectory import TrajectoryRenderer

    mesh = write_demo_object(tmp_path_factory.mktemp("trajectory"))
    config = {"target": {"count": [1, 1], "distance_m": [0.4, 0.5], "truncation_prob": 0.0}}
    with FrameGenerator(mesh, size=(160, 120), config=config, class_name=DEMO_CLASS_NAME, depth_noise=True,
                        seed=3) as gen:
        own = gen.render_frame(2)
    with FrameGenerator(mesh, size=(160, 120), config=config, class_name=DEMO_CLASS_NAME, depth_noise=True,
                        seed=3) as gen, TrajectoryRenderer(gen) as traj:
        seq = list(traj.sequence(2, 4, sweep_deg=30.0))
    return own, seq


def test_the_first_view_is_the_generators_frame(views):
    own, seq = views
    a, b = own.annotation.objects[0], seq[0].annotation.objects[0]
    assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t)
    assert np.array_equal(own.depth_clean, seq[0].depth_clean)


def test_the_scene_turns_about_the_target(views):
    _, seq = views
    poses = [(f.annotation.objects[0].R, f.annotation.objects[0].t) for f in seq]
    turned = [np.degrees(np.arccos(np.clip((np.trace(poses[0][0].T @ R) - 1) / 2, -1, 1))) for R, _ in poses]
    assert turned[0] == pytest.approx(0.0, abs=1e-3) and turned[-1] == pytest.approx(30.0, abs=1.0)
    assert all(np.linalg.norm(t - poses[0][1]) < 0.05 for _, t in poses)  # the target stays in view


def test_each_views_annotation_is_its_pose(views):
    _, seq = views
    for f in seq:
        o = f.annotation.objects[0]
        size, centre = f.target.cuboid_size, f.target.cuboid_center
        assert np.allclose(project_points(cuboid_keypoints(size, centre), f.annotation.K, o.R, o.t),
                           o.projected_cuboid, atol=1e-3)
        assert (f.depth_clean[f.seg == 1] > 0).all() and (f.seg == 1).sum() > 50


def test_orbit_starts_at_rest():
    poses = orbit_poses(5, 40.0, 10.0)
    assert np.allclose(poses[0], np.eye(4)) and len(poses) == 5
