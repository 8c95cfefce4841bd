"""Test helper (not a test file): lite models briefly fitted so that their maps detect a box.

Untrained networks output near-zero maps: nothing decodes, so comparing the detections of two
backends would compare empty lists. Here a lite network is fitted for a few dozen Adam steps
to the belief/affinity targets of ONE image whose cuboid keypoints are known, which is enough
for its maps to hold one clean instance at that image. The fit is deterministic (seeded) and
takes a few seconds. Two images:

* :func:`scene` / :func:`fit_lite_checkpoint`: a drawn Ketchup box (one thread);
* :func:`fit_demo_checkpoint`: demo scene (seed, 0) of `dope-hope demo`, which renders scene i
  of seed S deterministically, so the fitted network detects the box there: tests get a real
  detection (with a pose to score) without the shipped, trained weights.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

IMAGE_HW = (96, 128)
CLASS_NAME = "Ketchup"
K = np.array([[110.0, 0.0, 63.5], [0.0, 110.0, 47.5], [0.0, 0.0, 1.0]])
#: Network input (H, W) of the demo model: the demo's 640x480 scenes at 1/4.
DEMO_INPUT_HW = (120, 160)


def scene() -> tuple[np.ndarray, np.ndarray]:
    """(rgb (96, 128, 3) uint8, keypoints (9, 2) image px) of the Ketchup box at a fixed pose."""
    from scipy.spatial.transform import Rotation

    from dope_hope.catalog import get_object
    from dope_hope.geometry import CUBOID_EDGES, cuboid_keypoints, project_points

    size = get_object(CLASS_NAME).size_array
    R = Rotation.from_euler("xyz", [25, -35, 10], degrees=True).as_matrix()
    t = np.array([0.0, 0.0, 0.42])
    kp = project_points(cuboid_keypoints(size), K, R, t)
    rgb = np.full(IMAGE_HW + (3,), 90, np.uint8)
    rgb[::8] = 60  # some background texture
    hull = cv2.convexHull(np.round(kp[:8]).astype(np.int32))
    cv2.fillConvexPoly(rgb, hull, (200, 40, 40))
    for a, b in CUBOID_EDGES:
        cv2.line(rgb, tuple(int(v) for v in np.round(kp[a])), tuple(int(v) for v in np.round(kp[b])),
                 (250, 250, 250), 1)
    for k, p in enumerate(kp[:8]):  # a distinct colour per corner: corner identity is visible
        cv2.circle(rgb, tuple(int(v) for v in np.round(p)), 2, (30 * k, 255 - 30 * k, 120), -1)
    return rgb, kp


def fit_lite_model(rgb: np.ndarray, kp: np.ndarray, input_hw: tuple[int, int], steps: int):
    """A lite network (config "lite" at ``input_hw``) fitted with ``steps`` Adam steps to the
    belief/affinity targets of one image: rgb (H, W, 3) uint8 of size ``input_hw``, kp (9, 2)
    image px. Returns (model in eval mode, its config)."""
    import torch

    from dope_hope.config import load_config
    from dope_hope.maps.targets import make_targets
    from dope_hope.model.network import build_model, normalize_image

    torch.manual_seed(0)
    cfg = load_config("lite")
    cfg["input"]["size"] = list(input_hw)
    cfg["model"]["head"] = 50  # stride 8: what the Isaac ROS layout and the x8 tests need
    model = build_model(cfg)
    belief, affinity = make_targets(kp[None], input_hw, model.stride, sigma=1.0, radius=1.0)
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
    return model, cfg


def fit_lite_checkpoint(path: Path, steps: int = 60) -> Path:
    """Fit a lite network to :func:`scene`'s targets and save it as a dope-hope checkpoint."""
    import torch

    from dope_hope.model.checkpoint import save_checkpoint

    torch.set_num_threads(1)
    rgb, kp = scene()
    model, cfg = fit_lite_model(rgb, kp, IMAGE_HW, steps)
    save_checkpoint(path, model, cfg, {"class_name": CLASS_NAME})
    return path


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
