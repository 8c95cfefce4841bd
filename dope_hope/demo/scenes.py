"""The demo's scenes: the distribution of configs/demo.yaml at 640x480, each scene with the box
at least half visible.

Scene ``i`` of seed ``S`` is frame ``i`` of a synth dataset with seed ``S`` (the frames of
``dope-hope synth --config demo --seed S``) when its box is at least ``min_visibility``
visible (``visibility`` of the annotation: visible pixels over the pixels of the box rendered
alone, so distractors in front lower it). Otherwise the scene is drawn again, as frame ``i``
of seed :func:`redraw_seed` ``(S, i, k)`` for k = 1, 2, ... (the frame JSON records the seed
it came from); after ``attempts`` draws the most visible one is kept and reported as such.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dope_hope.synth import FrameGenerator, SynthFrame

#: Synth config of the demo scenes (configs/demo.yaml, merged over configs/synth.yaml).
DEMO_CONFIG = "demo"
#: (W, H) of the rendered scenes (the RealSense D415 colour camera's default mode).
IMAGE_SIZE = (640, 480)
#: Least visible fraction of the box in a demo scene (below it the scene is drawn again).
MIN_VISIBILITY = 0.5
#: Draws of one scene at most.
MAX_ATTEMPTS = 20


@dataclass
class DemoScene:
    """One demo scene: the rendered frame, the synth seed it is frame ``frame.index`` of, how
    many draws it took (1 = the plain frame of the demo seed) and the visibility it needed."""

    frame: SynthFrame
    seed: int
    draws: int
    min_visibility: float = MIN_VISIBILITY

    @property
    def visibility(self) -> float:
        """Visible fraction of the (one) box, 0 when the scene has none."""
        return min((o.visibility if o.visibility is not None else 1.0 for o in self.frame.annotation.objects),
                   default=0.0)

    @property
    def measurable(self) -> bool:
        """Whether the box is visible enough for the scene to count."""
        return self.visibility >= self.min_visibility


def redraw_seed(seed: int, index: int, draw: int) -> int:
    """Synth seed of draw ``draw`` (>= 1) of scene ``index`` of a demo with ``seed`` (31 bits)."""
    return int(np.random.SeedSequence([int(seed), int(index), int(draw)]).generate_state(1)[0] & 0x7FFFFFFF)


def render_scene(gen: FrameGenerator, index: int, min_visibility: float = MIN_VISIBILITY,
                 attempts: int = MAX_ATTEMPTS) -> DemoScene:
    """Scene ``index`` of the generator's seed with the box at least ``min_visibility`` visible
    (see the module docstring); the most visible of ``attempts`` draws when none is."""
    best: DemoScene | None = None
    for draw in range(attempts):
        seed = gen.seed if draw == 0 else redraw_seed(gen.seed, index, draw)
        scene = DemoScene(gen.render_frame(index, seed=seed), seed, draw + 1, min_visibility)
        if scene.measurable:
            return scene
        if best is None or scene.visibility > best.visibility:
            best = scene
    best.draws = attempts
    return best
