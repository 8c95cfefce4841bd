"""RealSense-like depth noise: error growth with depth, quantization, holes at edges/shadows/dark."""
from __future__ import annotations

import numpy as np

from dope_hope.geometry import intrinsics_matrix
from dope_hope.synth.depth_noise import add_realsense_noise, depth_edges, stereo_shadow

H, W = 120, 160
K = intrinsics_matrix(150.0, 150.0, 79.5, 59.5)
GRAY = np.full((H, W, 3), 128, np.uint8)


def _plane(z: float) -> np.ndarray:
    return np.full((H, W), z, np.float32)


def test_error_is_millimetres_at_half_a_metre_and_grows_with_depth():
    near = add_realsense_noise(_plane(0.5), GRAY, K, 0)
    far = add_realsense_noise(_plane(1.5), GRAY, K, 0)
    v_near, v_far = near > 0, far > 0
    assert v_near.mean() > 0.95 and v_far.mean() > 0.95
    # at this image's focal length (150 px) sigma is 2.4 mm at 0.5 m
    assert np.mean(np.abs(near[v_near] - 0.5) < 0.005) > 0.95
    # modelled as a D415 at 640x480 (fx 615) whose depth was resized: sigma 0.6 mm
    native = add_realsense_noise(_plane(0.5), GRAY, K, 0, stereo_fx_px=615.0)
    assert np.mean(np.abs(native[native > 0] - 0.5) < 0.002) > 0.99
    # sigma_z ~ z^2 * sigma_d / (fx * b): 9x from 0.5 m to 1.5 m
    s_near, s_far = np.std(near[v_near]), np.std(far[v_far])
    assert s_far > 4.0 * s_near
    expected = 1.5**2 * 0.08 / (150.0 * 0.055)
    assert 0.5 * expected < s_far < 2.0 * expected


def test_disparity_is_quantized():
    out = add_realsense_noise(_plane(0.8), None, K, 1, subpixel_sigma_px=0.3, dropout_prob=0.0)
    d = 150.0 * 0.055 / out[out > 0].astype(np.float64)
    steps = d / (1.0 / 32.0)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)


def test_pixels_at_depth_edges_are_dropped():
    z = _plane(1.0)
    z[:, 80:] = 0.6   # a depth step along column 80
    out = add_realsense_noise(z, GRAY, K, 2, stereo_shadow_enabled=False, dropout_prob=0.0)
    near_edge = np.zeros((H, W), bool)
    near_edge[:, 79:81] = True
    far_from_edge = np.zeros((H, W), bool)
    far_from_edge[:, :60] = True
    far_from_edge[:, 100:] = True
    assert (out[near_edge] == 0).mean() > 0.6
    assert (out[far_from_edge] == 0).mean() < 0.01
    edges = depth_edges(z, 0.02)
    assert edges[:, 79:81].all() and not edges[:, :78].any() and not edges[:, 82:].any()


def test_stereo_shadow_left_of_near_objects():
    z = _plane(1.0)
    z[40:80, 60:100] = 0.5      # near box: disparity 16.5 px vs 8.25 px behind it
    disp = np.where(z > 0, 150.0 * 0.055 / z, 0.0)
    shadow = stereo_shadow(disp)
    # the band of background just left of the box (about 8 px wide) is hidden from the right imager
    assert shadow[40:80, 53:60].all()
    assert not shadow[40:80, 100:].any() and not shadow[:40].any() and not shadow[40:80, 60:100].any()
    assert not shadow[40:80, :50].any()
    out = add_realsense_noise(z, GRAY, K, 3, edge_drop_prob=0.0, dropout_prob=0.0)
    assert (out[40:80, 53:60] == 0).all()


def test_dark_and_specular_surfaces_lose_depth():
    rgb = GRAY.copy()
    rgb[:, :40] = 5        # black
    rgb[:, 120:] = 255     # saturated highlight
    out = add_realsense_noise(_plane(0.7), rgb, K, 4, dark_drop_prob=1.0, specular_drop_prob=1.0,
                              dropout_prob=0.0)
    assert (out[:, :40] == 0).all() and (out[:, 120:] == 0).all()
    assert (out[:, 50:110] > 0).mean() > 0.99


def test_missing_input_stays_missing_and_output_is_reproducible():
    z = _plane(0.9)
    z[10:20, 10:20] = 0.0
    z[30, 30] = np.nan
    a = add_realsense_noise(z, GRAY, K, np.random.default_rng(7))
    b = add_realsense_noise(z, GRAY, K, np.random.default_rng(7))
    c = add_realsense_noise(z, GRAY, K, np.random.default_rng(8))
    assert a.dtype == np.float32 and a.shape == (H, W)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert (a[10:20, 10:20] == 0).all() and a[30, 30] == 0
    out = add_realsense_noise(_plane(0.1), GRAY, K, 0)   # closer than the minimum range
    assert (out == 0).all()
