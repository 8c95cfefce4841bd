"""The demo's scenes (dope_hope.demo.scenes) show the box at least half visible, and a scene that
cannot is left out of the count (dope_hope.demo.report.summary_lines)."""
from __future__ import annotations

import pytest

from dope_hope.demo.report import SceneResult, summary_lines
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE, MIN_VISIBILITY, redraw_seed, render_scene

#: A demo seed whose scene 2 hides the box behind a distractor (21 % visible in its first draw).
SEED, HIDDEN = 1668961097, 2


@pytest.fixture(scope="module")
def gen(tmp_path_factory):
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object
    from dope_hope.synth import FrameGenerator

    mesh = write_demo_object(tmp_path_factory.mktemp("demo_mesh"))
    with FrameGenerator(mesh, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME, seed=SEED) as g:
        yield g


def test_a_hidden_box_is_drawn_again_and_a_visible_one_is_kept(gen):
    first = gen.render_frame(HIDDEN)
    assert first.annotation.objects[0].visibility < MIN_VISIBILITY  # the scene that needs a redraw
    scene = render_scene(gen, HIDDEN)
    assert scene.draws > 1 and scene.measurable and scene.visibility >= MIN_VISIBILITY
    assert scene.seed == redraw_seed(SEED, HIDDEN, scene.draws - 1) and scene.frame.index == HIDDEN
    # the frame is the synth frame of the seed it records (what its JSON says)
    again = gen.render_frame(HIDDEN, seed=scene.seed)
    assert (again.rgb == scene.frame.rgb).all()
    kept = render_scene(gen, 0)  # its box is well visible: the plain frame of the demo seed
    assert kept.draws == 1 and kept.seed == SEED and (kept.frame.rgb == gen.render_frame(0).rgb).all()


def test_a_box_that_stays_hidden_is_reported_not_counted(gen):
    scene = render_scene(gen, HIDDEN, attempts=1)
    assert scene.draws == 1 and not scene.measurable
    results = [SceneResult("000000.png", found=True, found_no_ls=True, found_icp=True),
               SceneResult("000001.png", measurable=scene.measurable)]
    lines = summary_lines(results, with_onnx=False)
    assert lines[0].startswith("found 1/1 scenes with ADD-H < 2 cm (with -LS; without -LS: 1/1; with -LS + ICP: 1/1)")
    assert "left out: 1 scene(s) whose box stayed less than half visible" in lines[1]
