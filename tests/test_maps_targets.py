"""targets: Gaussian belief maps and affinity fields, and their round trip through decode."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dope_hope.maps.grid import image_to_map, map_to_image
from dope_hope.maps.peaks import find_peaks
from dope_hope.maps.targets import (
    affinity_fields,
    belief_maps,
    head_defaults,
    make_targets,
)


def _separated_keypoints(rng, n_inst, hw, min_sep, margin=0.0):
    """(n_inst, 9, 2) keypoints inside the image with same-type keypoints >= min_sep apart."""
    H, W = hw
    kp = np.zeros((n_inst, 9, 2))
    for k in range(9):
        pts = []
        while len(pts) < n_inst:
            p = np.array([rng.uniform(-margin, W - 1 + margin), rng.uniform(-margin, H - 1 + margin)])
            if all(np.linalg.norm(p - q) >= min_sep for q in pts):
                pts.append(p)
        kp[:, k] = pts
    return kp


def test_belief_peak_is_one_at_a_cell_centre_and_absent_rows_are_empty():
    stride = 8
    kp = np.full((2, 9, 2), np.nan)
    kp[0] = map_to_image(np.array([[10.0, 7.0]] * 9), stride)  # exactly on cell (x=10, y=7)
    b = belief_maps(kp, (20, 30), stride, sigma=1.0)
    assert b.shape == (9, 20, 30) and b.dtype == np.float32
    assert b[:, 7, 10] == pytest.approx(1.0)
    assert b[:, 7, 11] == pytest.approx(np.exp(-0.5), rel=1e-6)  # one sigma away
    assert np.unravel_index(np.argmax(b[3]), b[3].shape) == (7, 10)
    assert np.all(belief_maps(np.full((1, 9, 2), np.nan), (20, 30), stride, 1.0) == 0)
    assert np.all(belief_maps(np.zeros((0, 9, 2)), (20, 30), stride, 1.0) == 0)


def test_overlapping_instances_take_the_maximum_not_the_sum():
    kp = np.full((2, 9, 2), np.nan)
    kp[0, 0] = [40.0, 40.0]
    kp[1, 0] = [44.0, 40.0]
    both = belief_maps(kp, (16, 16), 4, sigma=2.0)
    one = belief_maps(kp[:1], (16, 16), 4, sigma=2.0)
    two = belief_maps(kp[1:], (16, 16), 4, sigma=2.0)
    np.testing.assert_allclose(both, np.maximum(one, two))
    assert both.max() <= 1.0


def test_keypoints_outside_the_image_leave_their_tails_inside():
    kp = np.full((1, 9, 2), np.nan)
    kp[0, 0] = [-12.0, 100.0]  # 1.5 cells left of the image at stride 8
    kp[0, 1] = [100.0, 400 + 20.0]  # below the image
    b, _ = make_targets(kp, (400, 400), 8, sigma=2.0, radius=1.0)
    assert b[0, :, 0].max() > 0.5 and b[0, :, 0].max() < 1.0
    assert b[1, -1, :].max() > 0.3
    assert b[0, :, 0].argmax() == round(image_to_map(np.array([0, 100.0]), 8)[1])


def test_affinity_is_the_unit_vector_towards_the_centroid_inside_the_radius_only():
    stride = 1
    kp = np.full((1, 9, 2), np.nan)
    kp[0, :8] = [[10.0, 10.0]] * 8
    kp[0, 8] = [30.0, 25.0]
    a = affinity_fields(kp, (40, 40), stride, radius=2.0)
    assert a.shape == (16, 40, 40) and a.dtype == np.float32
    norm = np.hypot(a[0], a[1])
    yy, xx = np.mgrid[0:40, 0:40]
    inside = (xx - 10) ** 2 + (yy - 10) ** 2 <= 4
    np.testing.assert_allclose(norm[inside], 1.0, atol=1e-6)
    assert np.all(norm[~inside] == 0)
    for y, x in zip(*np.nonzero(inside)):
        expected = np.array([30.0 - x, 25.0 - y])
        np.testing.assert_allclose([a[0, y, x], a[1, y, x]], expected / np.linalg.norm(expected), atol=1e-6)


def test_overlapping_affinities_are_summed_then_renormalized():
    kp = np.full((2, 9, 2), np.nan)
    kp[:, 0] = [20.0, 20.0]
    kp[0, 8] = [60.0, 20.0]  # +x
    kp[1, 8] = [20.0, 60.0]  # +y
    a = affinity_fields(kp, (80, 80), 1, radius=0.5)
    np.testing.assert_allclose(a[0:2, 20, 20], [np.sqrt(0.5), np.sqrt(0.5)], atol=1e-6)
    # An instance without a centroid contributes nothing.
    kp[1, 8] = np.nan
    a = affinity_fields(kp, (80, 80), 1, radius=0.5)
    np.testing.assert_allclose(a[0:2, 20, 20], [1.0, 0.0], atol=1e-6)


def test_make_targets_sizes_and_per_head_defaults():
    kp = np.array([[[50.0, 60.0]] * 9])
    b, a = make_targets(kp, (400, 320), 8)
    assert b.shape == (9, 50, 40) and a.shape == (16, 50, 40)
    assert head_defaults(8) == (0.5, 1.0) and head_defaults(1) == (4.0, 8.0)
    np.testing.assert_array_equal(b, belief_maps(kp, (50, 40), 8, 0.5))


@pytest.mark.parametrize("stride,sigma,hw", [(8, 2.0, (400, 400)), (8, 0.5, (400, 400)),
                                             (1, 4.0, (120, 160)), (1, 8.0, (120, 160))])
def test_decoded_peaks_recover_every_keypoint_within_a_small_fraction_of_a_pixel(stride, sigma, hw):
    """Encoding (targets) and decoding (peaks.find_peaks) share one convention: no drift."""
    rng = np.random.default_rng(stride * 100 + int(sigma * 10))
    # Same-type keypoints of different instances far enough apart not to merge.
    min_sep = 2.5 * np.sqrt(sigma**2 + 1.0) * stride + 2 * stride
    for _ in range(5):
        kp = _separated_keypoints(rng, 3, hw, min_sep)
        b, _ = make_targets(kp, hw, stride, sigma=sigma, radius=1.0)
        peaks = find_peaks(b)
        uv = map_to_image(peaks.xy, stride)
        assert len(uv) == kp.shape[0] * 9  # no spurious peaks
        for k in range(9):
            got = uv[peaks.channel == k]
            d = np.linalg.norm(got[:, None] - kp[None, :, k], axis=2)
            assert d.min(axis=0).max() < 0.05, f"keypoint {k}: {d.min(axis=0)} px"  # << 1 px


@settings(max_examples=40, deadline=None)
@given(
    u=st.lists(st.floats(0.0, 399.0), min_size=9, max_size=9),
    v=st.lists(st.floats(0.0, 295.0), min_size=9, max_size=9),
    stride=st.sampled_from([8, 1]),
)
def test_any_subpixel_keypoint_inside_the_image_is_recovered_within_one_pixel(u, v, stride):
    kp = np.stack([u, v], axis=1)[None]
    hw = (296, 400)  # network inputs are multiples of 8
    sigma = 2.0 if stride == 8 else 4.0
    b, _ = make_targets(kp, hw, stride, sigma=sigma, radius=1.0)
    peaks = find_peaks(b)
    uv = map_to_image(peaks.xy, stride)
    for k in range(9):
        got = uv[peaks.channel == k]
        assert len(got) == 1
        assert np.linalg.norm(got[0] - kp[0, k]) < 1.0


def test_keypoints_outside_the_image_produce_no_peak_inside_it():
    stride, hw = 8, (400, 400)
    kp = np.full((1, 9, 2), np.nan)
    kp[0, 0] = [-10.0, 200.0]     # 1.3 cells beyond the left edge
    kp[0, 1] = [200.0, 410.0]     # beyond the bottom edge
    kp[0, 2] = [420.0, -15.0]     # beyond a corner
    kp[0, 3] = [-30.0, 100.0]     # further out
    kp[0, 4] = [2.0, 3.0]         # inside, at the very edge: must be kept
    b, _ = make_targets(kp, hw, stride, sigma=2.0, radius=1.0)
    assert b[0].max() > 0.3 and b[1].max() > 0.3 and b[2].max() > 0.1  # tails are there
    peaks = find_peaks(b)
    assert set(peaks.channel.tolist()) == {4}
    np.testing.assert_allclose(map_to_image(peaks.xy, stride)[0], [2.0, 3.0], atol=0.05)
