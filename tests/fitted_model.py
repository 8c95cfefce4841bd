"""Test helper (not a test file): lite models briefly fitted so that their maps detect a box.

Untrained networks output near-zero maps: nothing decodes, so comparing the detections of two
backends would compare empty lists. Here a lite network is fitted for a few dozen Adam steps
to the belief/affinity targets of ONE image whose cuboid keypoints are known, which is enough
for its maps to hold one clean instance at that image. The fit is deterministic (seeded) and
takes a few seconds. Two images:

* :func:`scene` / :func:`fit_lite_checkpoint`: a drawn Ketchup box (one thread), from
  bench/fit_one.py (which bench/cpu_inference.py uses too: bench/ may not import tests/);
* :func:`fit_demo_checkpoint`: demo scene (seed, 0) of `dope-hope demo`, which renders scene i
  of seed S deterministically, so the fitted network detects the box there: tests get a real
  detection (with a pose to score) without the shipped, trained weights.
"""
from __future__ import annotations

import sys
from pathlib import Path

import cv2

BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(BENCH) not in sys.path:  # the bench helpers, as tests/test_bench_losses.py loads them
    sys.path.insert(0, str(BENCH))

from fit_one import CLASS_NAME, IMAGE_HW, K, fit_lite_checkpoint, fit_lite_model
from fit_one import box_scene as scene

__all__ = ["CLASS_NAME", "DEMO_INPUT_HW", "IMAGE_HW", "K", "fit_demo_checkpoint", "fit_lite_checkpoint",
           "fit_lite_model", "scene"]

#: Network input (H, W) of the demo model: the demo's 640x480 scenes at 1/4.
DEMO_INPUT_HW = (120, 160)


def fit_demo_checkpoint(path: Path, seed: int, steps: int = 80) -> Path:
    """A lite network fitted to the belief/affinity targets of demo scene (seed, 0), saved at path."""
    from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE, render_scene
    from dope_hope.demo_object import DEMO_CLASS_NAME, DEMO_SIZE_M, write_demo_object
    from dope_hope.model.checkpoint import make_object_info, save_checkpoint
    from dope_hope.synth import FrameGenerator

    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = write_demo_object(path.parent / "fit_mesh")
    with FrameGenerator(mesh, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME, seed=seed) as gen:
        frame = render_scene(gen, 0).frame
    H, W = DEMO_INPUT_HW
    s = W / frame.rgb.shape[1]
    rgb = cv2.resize(frame.rgb, (W, H), interpolation=cv2.INTER_AREA)
    kp = s * (frame.annotation.objects[0].projected_cuboid + 0.5) - 0.5
    model, cfg = fit_lite_model(rgb, kp, DEMO_INPUT_HW, steps)
    save_checkpoint(path, model, cfg, make_object_info(DEMO_CLASS_NAME, DEMO_SIZE_M))
    return path
