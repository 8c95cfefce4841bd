"""Sensor artefacts of the synthetic images (dope_hope/synth/sensor.py): each within its bounds."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dope_hope.synth.postprocess import post_process
from dope_hope.synth.sensor import (
    EFFECT_PROBS,
    disc_kernel,
    jpeg,
    motion_kernel,
    sensor_artifacts,
    to_linear,
    to_srgb,
)
from dope_hope.synth.settings import load_synth_config


@pytest.fixture(scope="module")
def post_cfg():
    return load_synth_config().post


def only(cfg, **on):
    """``cfg`` with every sensor effect off except those given (prob 1) and the given ranges."""
    return replace(cfg, **{**{k: 0.0 for k in EFFECT_PROBS}, **on})


def grey(v: int, h: int = 60, w: int = 80) -> np.ndarray:
    return np.full((h, w, 3), v, np.uint8)


def test_transfer_function_round_trips():
    v = np.arange(256, dtype=np.uint8)[None, :, None].repeat(3, axis=2)
    assert np.array_equal(to_srgb(to_linear(v)), v)


def test_all_effects_off_returns_the_image_unchanged(post_cfg):
    img = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    assert sensor_artifacts(np.random.default_rng(1), img, only(post_cfg)) is img


def test_same_generator_state_gives_the_same_image(post_cfg):
    img = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    cfg = replace(post_cfg, **{k: 1.0 for k in EFFECT_PROBS})
    a = post_process(np.random.default_rng(5), img, cfg)
    b = post_process(np.random.default_rng(5), img, cfg)
    c = post_process(np.random.default_rng(6), img, cfg)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_one_effect_off_leaves_the_others_draws(post_cfg):
    """Every number is drawn whatever the probabilities: another effect's range changes nothing."""
    img = grey(120)
    cfg = only(post_cfg, shot_noise_prob=1.0)
    a = sensor_artifacts(np.random.default_rng(3), img, cfg)
    b = sensor_artifacts(np.random.default_rng(3), img, replace(cfg, jpeg_quality=[10, 20], defocus_radius_px=[3, 4]))
    assert np.array_equal(a, b) and not np.array_equal(a, img)


def test_exposure_is_a_gain_in_linear_light(post_cfg):
    cfg = only(post_cfg, exposure_prob=1.0, exposure_ev=[1.0, 1.0], white_balance=[1.0, 1.0])
    out = sensor_artifacts(np.random.default_rng(0), grey(118), cfg)
    expected = to_srgb(2.0 * to_linear(grey(118)))
    assert np.array_equal(out, expected) and 155 <= int(out[0, 0, 0]) <= 165
    # white balance moves red and blue against green
    cfg = only(post_cfg, exposure_prob=1.0, exposure_ev=[0.0, 0.0], white_balance=[0.8, 0.8])
    out = sensor_artifacts(np.random.default_rng(0), grey(118), cfg)
    assert out[0, 0, 1] == 118 and out[0, 0, 0] < 118 and out[0, 0, 2] < 118


def test_vignetting_darkens_the_corners_by_its_strength(post_cfg):
    cfg = only(post_cfg, vignetting_prob=1.0, vignetting=[0.3, 0.3])
    out = sensor_artifacts(np.random.default_rng(0), grey(200, 61, 81), cfg)
    lin = to_linear(out)[..., 1]
    x = to_linear(grey(200))[0, 0, 1]
    assert abs(lin[30, 40] / x - 1.0) < 0.01                  # centre untouched
    assert abs(lin[0, 0] / x - 0.7) < 0.02                   # corner loses 30 %
    assert lin[30, 0] > lin[0, 0]


def test_noise_grows_with_the_signal_as_shot_noise(post_cfg):
    shot, read = 0.004, 0.001
    cfg = only(post_cfg, shot_noise_prob=1.0, shot_noise=[shot, shot], read_noise=[read, read])
    for v in (60, 200):
        img = grey(v, 200, 200)
        out = to_linear(sensor_artifacts(np.random.default_rng(v), img, cfg)).astype(np.float64)
        x = float(to_linear(img)[0, 0, 0])
        # measured variance of the linear signal (sRGB rounding adds a little) ~ shot * x + read^2
        assert out.var() == pytest.approx(shot * x + read ** 2, rel=0.15)
        assert abs(out.mean() - x) < 0.01


def test_chromatic_aberration_moves_red_and_blue_apart_towards_the_edge(post_cfg):
    img = np.zeros((61, 121, 3), np.uint8)
    img[:, 110] = 255                                        # a white line near the right edge
    cfg = only(post_cfg, chromatic_prob=1.0, chromatic_px=[1.0, 1.0])
    out = to_linear(sensor_artifacts(np.random.default_rng(0), img, cfg))[30]
    cols = np.arange(out.shape[0])
    cx = {c: float((cols * out[:, c]).sum() / out[:, c].sum()) for c in range(3)}
    corner = np.hypot(60, 30)
    assert cx[1] == pytest.approx(110, abs=0.05)
    assert cx[0] - 110 == pytest.approx(50 / corner, abs=0.1)  # red outwards, in proportion
    assert 110 - cx[2] == pytest.approx(50 / corner, abs=0.1)  # to the distance from the centre


def test_blur_kernels_are_normalized_and_shaped():
    d = disc_kernel(2.0)
    assert d.shape == (5, 5) and d.sum() == pytest.approx(1.0) and d[2, 2] == d.max() and d[0, 0] == 0
    m = motion_kernel(8.0, 0.0)                              # horizontal
    assert m.sum() == pytest.approx(1.0)
    rows = np.flatnonzero(m.sum(axis=1) > 1e-3)
    cols = np.flatnonzero(m.sum(axis=0) > 1e-3)
    assert len(rows) <= 2 and 7 <= len(cols) <= 10


def test_jpeg_is_applied_at_the_drawn_quality(post_cfg):
    yy, xx = np.mgrid[0:64, 0:64]
    img = np.stack([xx * 4, yy * 4, (xx + yy) * 2], axis=2).astype(np.uint8)
    cfg = only(post_cfg, jpeg_prob=1.0, jpeg_quality=[30, 30])
    out = sensor_artifacts(np.random.default_rng(0), img, cfg)
    assert np.array_equal(out, jpeg(img, 30)) and not np.array_equal(out, img)
    err = np.abs(out.astype(int) - img).mean()
    assert 0.2 < err < 6.0
    assert np.abs(jpeg(img, 95).astype(int) - img).mean() < err
