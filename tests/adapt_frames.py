"""Test helper (not a test file): a few RGB-D frames of one static demo-box scene at 320x240,
written as DOPE frames (their truth in the JSON), and the demo model that detects the box."""
from __future__ import annotations

from pathlib import Path

#: (W, H) of the frames.
SIZE = (320, 240)


def write_scene_frames(folder: Path, count: int = 3, seed: int = 11) -> tuple[Path, Path]:
    """``count`` DOPE frames (RGB, depth with RealSense-like noise, truth) of demo scenes in
    ``folder/frames`` and the demo box's mesh; returns (frames folder, mesh file)."""
    import dope_hope.model  # noqa: F401 - torchvision before the GL context
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    mesh = write_demo_object(folder / "mesh")
    still = {**PLAIN_OVERRIDES, "camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}}
    config = {**still, "target": {"count": [1, 1], "distance_m": [0.4, 0.5], "truncation_prob": 0.0}}
    with FrameGenerator(mesh, size=SIZE, config=config, class_name=DEMO_CLASS_NAME, depth_noise=True,
                        seed=seed) as gen:
        for i in range(count):
            gen.write_frame(folder / "frames", i)
    return folder / "frames", mesh


def demo_weights(tmp: Path) -> Path:
    """The shipped demo model, else a checkpoint fitted in seconds (tests/fitted_model.py)."""
    from fitted_model import fit_demo_checkpoint

    from dope_hope.assets import DEMO_WEIGHTS

    return DEMO_WEIGHTS if DEMO_WEIGHTS.is_file() else fit_demo_checkpoint(tmp / "fit" / "demo.pt", seed=7)
