"""Hard negatives (dope_hope/synth/hard_negatives.py): the target's size and colours, never annotated."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from dope_hope.errors import ConfigError
from dope_hope.synth.generate import FrameGenerator
from dope_hope.synth.hard_negatives import (
    TargetLook,
    palette_texture,
    shape_class,
    shuffled_texture,
    surface_colors,
)
from dope_hope.synth.primitives import primitive_shape
from dope_hope.synth.settings import load_synth_config

SIZE = (160, 120)
# Two targets and two look-alikes per frame, nothing else in the way.
CFG = {"target": {"count": [2, 2]}, "distractors": {"count": [0, 0], "occluder_prob": 0.0},
       "hard_negatives": {"count": [2, 2]}}


@pytest.fixture(scope="module")
def frames(shared_data: Path):
    with FrameGenerator(shared_data / "hope_ketchup" / "textured_simple.obj", size=SIZE, config=CFG,
                        seed=11) as g:
        yield g, [g.render_frame(i) for i in range(4)]


def test_shape_class_from_the_hull_fill():
    assert shape_class(trimesh.creation.box(extents=[0.1, 0.2, 0.05]), np.array([0.1, 0.2, 0.05])) == "box"
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.2, sections=32)
    assert shape_class(cyl, np.array([0.06, 0.06, 0.2])) == "cylinder"
    bottle = primitive_shape("bottle", np.array([0.03, 0.2]))
    assert shape_class(bottle, np.array([0.06, 0.06, 0.2])) == "bottle"


def test_surface_colours_come_from_vertex_colours_or_the_texture(shared_data: Path):
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    colors = np.tile(np.array([200, 20, 30, 255], np.uint8), (len(box.vertices), 1))
    assert np.all(surface_colors(box, None, colors) == [200, 20, 30])
    look = _ketchup_look(shared_data)
    assert look.shape == "bottle" and look.texture is not None
    # the Ketchup bottle is mostly red: its sampled colours are too
    assert np.median(look.colors[:, 0]) > np.median(look.colors[:, 1]) + 40


def _ketchup_look(shared_data: Path) -> TargetLook:
    from dope_hope.synth.assets import MeshAsset

    a = MeshAsset.load(shared_data / "hope_ketchup" / "textured_simple.obj")
    return TargetLook.of(a.mesh, a.texture, a.colors, a.cuboid_size)


def test_textures_reuse_the_targets_colours_not_its_layout(shared_data: Path):
    look = _ketchup_look(shared_data)
    rng = np.random.default_rng(0)
    pal = palette_texture(rng, look, 64)
    known = {tuple(c) for c in look.colors}
    assert pal.shape == (64, 64, 3) and {tuple(c) for c in pal.reshape(-1, 3)} <= known
    tex = np.ascontiguousarray(look.texture[:128, :128])
    small = TargetLook(look.size, look.shape, look.colors, tex)
    shuf = shuffled_texture(np.random.default_rng(1), small, 128, (4, 4))
    assert shuf.shape == tex.shape and not np.array_equal(shuf, tex)
    # the same pixels, rearranged in 32 x 32 tiles
    assert np.array_equal(np.sort(shuf.reshape(-1, 3), axis=0), np.sort(tex.reshape(-1, 3), axis=0))


def test_hard_negatives_are_rendered_and_never_annotated(frames):
    gen, fs = frames
    base = int(gen.cfg.output.seg_distractor_base)
    radius = gen.target.shape.radius
    seen = 0
    for f in fs:
        negs = [o for o in f.scene.objects if o.role == "hard_negative"]
        targets = [o for o in f.scene.objects if o.role == "target"]
        assert len(negs) >= 1
        assert len(f.annotation.objects) == len(targets)
        assert {o.instance_id for o in f.annotation.objects} == {t.seg_id for t in targets}
        for o in negs:
            assert o.seg_id > base
            # the target's size: radius within the jitter of the target's bounding sphere
            assert 0.6 * radius < o.radius < 1.4 * radius
            seen += int((f.seg == o.seg_id).sum() > 0)
        # their pixels carry distractor ids, never target ones
        target_ids = {t.seg_id for t in targets}
        assert not (set(np.unique(f.seg)) - target_ids - {0}) & set(range(1, base))
    assert seen >= 3


def test_hard_negatives_leave_the_rest_of_the_frame_unchanged(frames, shared_data: Path):
    """Their own random stream: switching them off changes nothing else (same targets, camera,
    background, and the same pixels wherever no look-alike is in front)."""
    gen, fs = frames
    cfg = dict(CFG, hard_negatives={"count": [0, 0]})
    with FrameGenerator(shared_data / "hope_ketchup" / "textured_simple.obj", size=SIZE, config=cfg,
                        seed=11) as g:
        f0 = g.render_frame(0)
    f1 = fs[0]
    assert np.array_equal(f0.annotation.K, f1.annotation.K)
    for a, b in zip(f0.annotation.objects, f1.annotation.objects):
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
    free = f1.seg < int(gen.cfg.output.seg_distractor_base)
    assert np.array_equal(f0.seg[free], f1.seg[free])


def test_frames_are_deterministic(frames, shared_data: Path):
    gen, fs = frames
    with FrameGenerator(shared_data / "hope_ketchup" / "textured_simple.obj", size=SIZE, config=CFG,
                        seed=11) as g:
        again = g.render_frame(2)
    assert np.array_equal(again.rgb, fs[2].rgb) and np.array_equal(again.seg, fs[2].seg)


@pytest.mark.parametrize("override, key", [
    ({"hard_negatives": {"count": [3, 1]}}, "hard_negatives.count"),
    ({"hard_negatives": {"same_shape_prob": 2.0}}, "hard_negatives.same_shape_prob"),
    ({"hard_negatives": {"textures": {"palette": 0, "shuffled": 0, "flat": 0}}}, "hard_negatives.textures"),
    ({"hard_negatives": {"texture_px": 0}}, "hard_negatives.texture_px"),
    ({"background": {"clutter": {"size": [0.3, 0.1]}}}, "background.clutter.size"),
    ({"background": {"clutter": {"resolution": 0.0}}}, "background.clutter.resolution"),
    ({"background": {"clutter_prob": -0.1}}, "background.clutter_prob"),
    ({"post": {"jpeg_quality": [50, 101]}}, "post.jpeg_quality"),
    ({"post": {"vignetting": [0.1, 1.0]}}, "post.vignetting"),
    ({"post": {"motion_blur_prob": "often"}}, "post.motion_blur_prob"),
    ({"hard_negatives": {"count": [0, 200]}}, "hard_negatives.count"),
    ({"hard_negatives": {"cuont": [0, 1]}}, "hard_negatives.cuont"),
])
def test_config_errors_name_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_synth_config(override)


def test_demo_scenes_keep_the_new_randomization_off():
    """configs/demo.yaml: `dope-hope demo`'s scenes keep clutter, hard negatives and sensor
    artefacts off (its figures compare with earlier demo models'); synth.yaml's defaults have all
    three on."""
    from dope_hope.config import merge
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    demo, default = load_synth_config("demo").to_dict(), load_synth_config().to_dict()
    assert merge(demo, PLAIN_OVERRIDES) == demo
    assert merge(default, PLAIN_OVERRIDES) != default
