"""dope_hope.refine.depth: the depth boundary converts once, records why depth is unusable,
and refuses nonsense settings."""
from __future__ import annotations

import numpy as np
import pytest

from dope_hope.errors import ConfigError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.refine.depth import DepthImage

K = intrinsics_matrix(500.0, 500.0, 159.5, 119.5)


def test_units_calibration_and_invalid_pixels():
    raw = np.full((240, 320), 1000, np.uint16)
    raw[0, 0] = 0
    d = DepthImage.from_raw(raw, K, depth_scale_m=0.001, calibration=0.98)
    assert d.usable and d.hw == (240, 320)
    assert d.metres[1, 1] == pytest.approx(0.98) and np.isnan(d.metres[0, 0])
    # Float depth is metres already; the scale applies to integer units only.
    f = DepthImage.from_raw(np.full((240, 320), 0.5, np.float32), K, depth_scale_m=0.001)
    assert f.metres[5, 5] == pytest.approx(0.5)


@pytest.mark.parametrize("depth, image_hw, reason", [
    (None, None, "no depth image"),
    (np.zeros((240, 320, 3), np.uint16), None, "2-D"),
    (np.full((240, 320), 1000, np.uint16), (480, 640), "the image is 640x480"),
    (np.full((120, 160), 1000, np.uint16), None, "K implies"),
    (np.zeros((240, 320), np.uint16), None, "no valid pixel"),
    (np.full((240, 320), 650.0, np.float32), None, "median is 650 m, beyond any depth camera's range (30 m): "
                                                  "wrong units? float depth is read as metres"),  # mm as floats
])
def test_unusable_depth_is_a_reason_not_an_exception(depth, image_hw, reason):
    d = DepthImage.from_raw(depth, K, image_hw=image_hw)
    assert not d.usable and reason in d.problem
    assert reason in d.problem_for(np.array([0.0, 0.0, 1.0]))


def test_a_wrong_depth_scale_is_a_reason():
    d = DepthImage.from_raw(np.full((240, 320), 650, np.uint16), K, depth_scale_m=1.0)  # mm read as m
    assert not d.usable and "integer depth is read in units of 1 m" in d.problem
    assert DepthImage.from_raw(np.full((240, 320), 25.0, np.float32), K).usable  # far, but a camera's range


def test_pose_behind_the_camera_is_refused_per_pose():
    d = DepthImage.from_raw(np.full((240, 320), 800, np.uint16), K)
    assert d.problem_for(np.array([0.0, 0.0, 0.7])) == ""
    assert "behind the camera" in d.problem_for(np.array([0.0, 0.0, -0.7]))


@pytest.mark.parametrize("kw", [{"depth_scale_m": float("nan")}, {"depth_scale_m": float("inf")},
                                {"depth_scale_m": 0.0}, {"calibration": 0.0}, {"calibration": -1.0},
                                {"calibration": float("nan")}])
def test_nonsense_scale_or_calibration_is_a_user_error(kw):
    with pytest.raises(ConfigError, match="depth (scale|calibration) must be a finite number > 0"):
        DepthImage.from_raw(np.full((240, 320), 800, np.uint16), K, **kw)
