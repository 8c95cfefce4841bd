"""Overlays: cuboid edges land on the projected keypoints; axes have the documented colours."""
from __future__ import annotations

import numpy as np
import pytest

from dope_hope.geometry import cuboid_keypoints, intrinsics_matrix, project_points
from dope_hope.viz import draw_axes, draw_cuboid, draw_keypoints, draw_label, montage

K = intrinsics_matrix(200.0, 200.0, 79.5, 59.5)


def _box_uv() -> np.ndarray:
    R = np.eye(3)
    t = np.array([0.0, 0.0, 0.5])
    return project_points(cuboid_keypoints(np.array([0.1, 0.15, 0.05])), K, R, t)


def test_draw_cuboid_draws_on_edges_only_and_copies():
    img = np.zeros((120, 160, 3), np.uint8)
    uv = _box_uv()
    out = draw_cuboid(img, uv, color=(0, 255, 0), thickness=1, draw_points=False)
    assert img.max() == 0  # input untouched
    # an edge midpoint is green, the area far outside the box is black
    mid = np.round((uv[0] + uv[1]) / 2).astype(int)
    assert out[mid[1], mid[0], 1] > 100
    assert out[:5, :5].max() == 0 and out[115:, 155:].max() == 0
    # only the green channel is used
    assert out[..., 0].max() == 0 and out[..., 2].max() == 0


def test_draw_cuboid_skips_missing_points_and_survives_far_points():
    img = np.zeros((60, 80, 3), np.uint8)
    uv = _box_uv() / 2
    uv[3] = np.nan
    out = draw_cuboid(img, uv)
    assert out.any()
    far = uv.copy()
    far[0] = [1e9, -1e9]
    assert draw_cuboid(img, far).shape == img.shape
    assert draw_cuboid(img, np.full((9, 2), np.nan)).max() == 0


def test_draw_axes_colours():
    img = np.zeros((120, 160, 3), np.uint8)
    R, t = np.eye(3), np.array([0.0, 0.0, 0.5])
    out = draw_axes(img, K, R, t, length=0.1, thickness=2)
    # x axis goes right from the centre: red; y axis goes down: green
    assert out[60, 79 + 30, 0] > 200 and out[60, 79 + 30, 1] < 60
    assert out[59 + 30, 80, 1] > 200 and out[59 + 30, 80, 0] < 60
    # behind the camera: nothing drawn
    assert draw_axes(img, K, R, np.array([0.0, 0.0, -1.0])).max() == 0


def test_keypoints_label_and_montage():
    img = np.zeros((40, 50, 3), np.uint8)
    kp = draw_keypoints(img, np.array([[10.0, 10.0], [np.nan, 3.0]]), labels=True)
    assert kp[10, 10].max() > 0
    lab = draw_label(img, "hi")
    assert lab[:10, :10].any()
    m = montage([img, np.zeros((20, 25), np.uint8), img], cols=2, gap=2)
    assert m.shape == (2 * 40 + 2, 2 * 50 + 2, 3)
    with pytest.raises(ValueError):
        montage([])


# overlay_detections / belief_montage (added with dope-hope infer)
def test_overlay_detections_draws_each_detection_in_its_class_colour():
    from types import SimpleNamespace

    from dope_hope.viz import class_color, overlay_detections

    size = np.array([0.1, 0.15, 0.05])
    det = SimpleNamespace(class_name="Ketchup", score=0.87, R=np.eye(3), t=np.array([0.0, 0.0, 0.5]),
                          cuboid_size_m=size, ls_applied=True)
    img = np.zeros((120, 160, 3), np.uint8)
    out = overlay_detections(img, [det], K)
    assert img.max() == 0 and out.shape == img.shape
    uv = _box_uv()
    mid = np.round((uv[4] + uv[5]) / 2).astype(int)  # a back edge: no axis crosses it
    assert np.abs(out[mid[1], mid[0]].astype(int) - class_color("Ketchup")).sum() < 60
    # the label sits above the box: something bright left of the box, above its top
    top = int(np.floor(uv[:, 1].min()))
    assert out[max(top - 14, 0):top, int(uv[:, 0].min()):].max() > 150
    assert class_color("Ketchup") == class_color("Ketchup") and class_color("Ketchup") != class_color("Mustard")
    empty = overlay_detections(img, [], K)
    assert empty[:20, :80].max() > 150  # "no detections"


def test_belief_montage_layout_and_peak_position():
    from dope_hope.viz import belief_montage

    belief = np.zeros((9, 12, 16), np.float32)
    belief[8, 3, 12] = 1.0  # centroid peak in the upper right
    image = np.full((120, 160, 3), 128, np.uint8)
    out = belief_montage(belief, image, cols=3, max_side=160)
    assert out.shape == (3 * 120 + 2 * 2, 3 * 160 + 2 * 2, 3)
    centroid_tile = out[2 * 122:2 * 122 + 120, 2 * 162:2 * 162 + 160].astype(int)
    corner_tile = out[0:120, 0:160].astype(int)
    below_label = np.abs(centroid_tile - 96).sum(2)[28:]  # the title box covers the top rows
    peak = np.unravel_index(np.argmax(below_label), below_label.shape)
    assert abs(peak[1] - 124.5) <= 3 and abs(peak[0] + 28 - 34.5) <= 3
    assert np.abs(corner_tile[30:] - 96).max() <= 1  # empty map: the dimmed image only
    with pytest.raises(ValueError):
        belief_montage(np.zeros((4, 4)))
