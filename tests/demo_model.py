"""Test helper (not a test file): a lite demo-box model fitted in seconds to one demo scene.

`dope-hope demo` renders scene i of seed S deterministically, so a network fitted to the
belief/affinity targets of scene (S, 0) detects the box there: tests get a real detection
(with a pose to score) without the shipped, trained weights.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import torch

#: Network input (H, W): the demo's 640x480 scenes at 1/4.
INPUT_HW = (120, 160)


def fit_demo_checkpoint(path: Path, seed: int, steps: int = 80) -> Path:
    """A lite network fitted to the belief/affinity targets of demo scene (seed, 0), saved at path."""
    from dope_hope.commands import demo as demo_cmd
    from dope_hope.config import load_config
    from dope_hope.demo_object import DEMO_CLASS_NAME, DEMO_SIZE_M, write_demo_object
    from dope_hope.model.checkpoint import make_object_info, save_checkpoint
    from dope_hope.model.network import build_model, normalize_image
    from dope_hope.synth import FrameGenerator
    from dope_hope.targets import make_targets

    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = write_demo_object(path.parent / "fit_mesh")
    with FrameGenerator(mesh, size=demo_cmd.IMAGE_SIZE, config=demo_cmd.DEMO_CONFIG,
                        class_name=DEMO_CLASS_NAME, seed=seed) as gen:
        frame = gen.render_frame(0)
    H, W = INPUT_HW
    s = W / frame.rgb.shape[1]
    rgb = cv2.resize(frame.rgb, (W, H), interpolation=cv2.INTER_AREA)
    kp = s * (frame.annotation.objects[0].projected_cuboid + 0.5) - 0.5
    torch.manual_seed(0)
    cfg = load_config("lite")
    cfg["input"]["size"] = list(INPUT_HW)
    model = build_model(cfg)
    belief, affinity = make_targets(kp[None], INPUT_HW, model.stride, sigma=1.0, radius=1.0)
    x = normalize_image(rgb)[None]
    tb, ta = torch.from_numpy(belief)[None], torch.from_numpy(affinity)[None]
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    model.train()
    for _ in range(steps):
        loss = sum(((b - tb) ** 2).mean() + ((a - ta) ** 2).mean() for b, a in model(x))
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    save_checkpoint(path, model, cfg, make_object_info(DEMO_CLASS_NAME, DEMO_SIZE_M))
    return path
