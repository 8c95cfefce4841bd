"""Table-top clutter backgrounds (dope_hope/synth/clutter.py, background.clutter_prob)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dope_hope.synth.background import BackgroundSource
from dope_hope.synth.clutter import box_sprite, clutter_image
from dope_hope.synth.settings import load_synth_config


@pytest.fixture(scope="module")
def bg_cfg():
    return load_synth_config().background


def test_clutter_is_deterministic_and_covers_the_background(bg_cfg):
    base = np.full((90, 120, 3), 128, np.uint8)
    cfg = replace(bg_cfg.clutter, count=[20, 20], blur_sigma_px=[0.0, 0.0])
    a = clutter_image(np.random.default_rng(0), base, cfg)
    b = clutter_image(np.random.default_rng(0), base, cfg)
    c = clutter_image(np.random.default_rng(1), base, cfg)
    assert a.shape == base.shape and a.dtype == np.uint8
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    changed = np.abs(a.astype(int) - base).max(axis=2) > 8
    assert 0.2 < changed.mean() < 1.0                         # a pile, not a new image
    # no objects (count 0): the background, untouched
    empty = clutter_image(np.random.default_rng(0), base, replace(cfg, count=[0, 0]))
    assert np.array_equal(empty, base)


def test_box_faces_facing_the_light_are_brighter():
    white = np.full((16, 16, 3), 255, np.uint8)
    light = np.array([0.0, 0.0, -1.0])                        # from the camera
    rgb, alpha = box_sprite(np.random.default_rng(3), 60.0, lambda: white, light, ambient=0.2)
    assert alpha.max() == pytest.approx(1.0) and alpha.mean() > 0.1
    inside = alpha > 0.99
    # shading = 0.2 + 0.8 * cos(angle to the camera): between ambient and full white, never above
    assert rgb[inside].min() >= 0.2 * 255 - 1 and rgb[inside].max() <= 255 + 1e-3
    assert rgb[inside].max() > 0.6 * 255                      # one visible face is within 60 deg


def test_background_source_draws_clutter_with_its_probability_only(bg_cfg, shared_data: Path):
    folder = shared_data / "backgrounds"
    off = BackgroundSource(replace(bg_cfg, clutter_prob=0.0), folder)
    on = BackgroundSource(replace(bg_cfg, clutter_prob=1.0), folder)
    a = off.sample(np.random.default_rng(4), 96, 72)
    b = on.sample(np.random.default_rng(4), 96, 72)
    assert a.shape == b.shape == (72, 96, 3) and not np.array_equal(a, b)
    # the clutter draws from its own child generator: switching it off leaves the crop, flips
    # and colour shift as they were, so the two differ only where the pile is
    same = (np.abs(a.astype(int) - b).max(axis=2) <= 2).mean()
    assert same > 0.05


def test_clutter_takes_photo_textures_when_asked(bg_cfg):
    calls = []

    def source(rng, px):
        calls.append(px)
        return np.zeros((px, px, 3), np.uint8) + np.array([0, 255, 0], np.uint8)

    base = np.zeros((60, 80, 3), np.uint8)
    cfg = replace(bg_cfg.clutter, photo_texture_prob=1.0, count=[15, 15], blur_sigma_px=[0.0, 0.0])
    img = clutter_image(np.random.default_rng(0), base, cfg, source)
    assert calls and set(calls) == {cfg.texture_px}
    assert img[..., 1].max() > 100 and img[..., 0].max() == 0 and img[..., 2].max() == 0
