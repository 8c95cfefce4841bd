"""peaks: sub-pixel belief peaks, their heights and the maps' noise floor."""
from __future__ import annotations

import numpy as np
import pytest

from dope_hope.maps.peaks import find_peaks, noise_floor


def test_a_peak_with_a_shoulder_is_fitted_at_its_raw_maximum_not_the_smoothed_one():
    """Smoothing (for detection) moves a skewed peak's cell towards its shoulder; the
    sub-cell fit must still happen around the raw maximum (a trained net's peaks are rarely
    symmetric: fitting at the smoothed cell put keypoints ~1 cell = 8 px off)."""
    h, w = 16, 20
    ys, xs = np.mgrid[0:h, 0:w].astype(float)

    def blob(x0, y0, s, a):
        return a * np.exp(-((xs - x0) ** 2 + (ys - y0) ** 2) / (2 * s * s))

    raw = np.zeros((9, h, w), np.float32)
    raw[0] = blob(8.3, 7.0, 0.7, 1.0) + blob(10.6, 7.0, 0.9, 0.8)  # keypoint + a strong shoulder
    for sigma in (1.0, 2.0):
        peaks = find_peaks(raw, 0.1, smooth_sigma=sigma)
        assert len(peaks.xy) == 1 and tuple(peaks.cell[0]) == (8, 7)
        assert abs(peaks.xy[0, 0] - 8.3) < 0.2 and peaks.xy[0, 1] == pytest.approx(7.0)


def test_a_peak_that_climbed_and_cannot_be_fitted_scores_its_raw_height():
    """Where the log-parabola fit fails (here: an empty cell on one side of the raw maximum),
    the score is the raw 3x3 maximum at the cell the peak climbed to, not 0: a noisy net's
    true corner scored 0 ranked behind noise peaks of its type."""
    raw = np.zeros((9, 12, 16), np.float32)
    raw[0, 6, 5:10] = [0.0, 1.0, 0.95, 0.95, 0.9]   # smoothing peaks right of the raw maximum
    raw[0, 5, 5:10] = raw[0, 7, 5:10] = [0.0, 0.5, 0.5, 0.5, 0.45]
    peaks = find_peaks(raw, 0.1, smooth_sigma=1.0)
    assert len(peaks.score) == 1 and tuple(peaks.cell[0]) == (6, 6)
    assert peaks.score[0] == pytest.approx(1.0)


def test_noise_floor_is_the_background_plus_robust_standard_deviations():
    rng = np.random.default_rng(0)
    maps = rng.normal(0.02, 0.1, (9, 60, 80)).astype(np.float32)
    maps[:, 20:23, 30:33] = 1.0  # a peak barely moves the median and the MAD
    np.testing.assert_allclose(noise_floor(maps, 4.0), 0.02 + 4.0 * 0.1, atol=0.04)
    np.testing.assert_allclose(noise_floor(np.zeros((9, 300, 400), np.float32), 4.0), 0.0)


@pytest.mark.parametrize("hw", [(60, 80), (6, 7)])  # (6, 7): smoothing wider than the map (scipy)
def test_peaks_of_stacked_maps_split_into_those_of_each_block(hw):
    """Several objects' belief maps searched at once (:func:`split_peaks`) give every block the
    peaks, in the order, of a search over that block alone: noisy maps with plateaus, NaN
    cells, a block with no peak, and a noise floor computed per channel."""
    from dope_hope.maps.peaks import split_peaks

    rng = np.random.default_rng(7)
    blocks = [(rng.random((9, *hw)) ** 6).astype(np.float32) for _ in range(4)]
    blocks[1][:, 2:4, 2:4] = 0.9                   # plateaus of equal maxima
    blocks[2][:] = 0.0                             # nothing above the threshold
    blocks[3][0, 1, 1] = np.nan
    for kwargs in ({"noise_sigmas": 0.0}, {"noise_sigmas": 4.0},
                   {"smooth_sigma": 0.0, "refine_on": "smoothed", "noise_sigmas": 0.0}):
        parts = split_peaks(find_peaks(np.concatenate(blocks), 0.1, **kwargs), len(blocks), 9)
        assert len(parts) == len(blocks)
        for block, part in zip(blocks, parts):
            alone = find_peaks(block, 0.1, **kwargs)
            for field in ("channel", "cell", "xy", "score"):
                np.testing.assert_array_equal(getattr(part, field), getattr(alone, field))
        assert len(parts[2].score) == 0 and sum(len(p.score) for p in parts) > 20
