"""Bench and test helper (not a benchmark, not shipped): a lite network fitted to one image in
seconds, a model whose maps detect a known box.

Untrained networks output near-zero maps: nothing decodes, so comparing the detections of two
backends (torch, ONNX fp32, INT8) would compare empty lists. Here a lite network is fitted
for a few dozen Adam steps to the belief/affinity targets of ONE image whose cuboid keypoints
are known, which is enough for its maps to hold one clean instance at that image. The fit is
deterministic (seeded) and takes a few seconds on one thread: :func:`box_scene` draws the
image (a Ketchup box), :func:`fit_lite_model` fits a network to any image's keypoints,
:func:`fit_lite_checkpoint` saves the fitted box model (tests, ``bench/cpu_inference.py``).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.config import load_config
from dope_hope.geometry import CUBOID_EDGES, cuboid_keypoints, project_points
from dope_hope.maps.targets import make_targets
from dope_hope.model.checkpoint import save_checkpoint
from dope_hope.model.network import build_model, normalize_image

#: (H, W) of :func:`box_scene` and the fitted model's input.
IMAGE_HW = (96, 128)
CLASS_NAME = "Ketchup"
#: Camera of :func:`box_scene`.
K = np.array([[110.0, 0.0, 63.5], [0.0, 110.0, 47.5], [0.0, 0.0, 1.0]])


def box_scene() -> tuple[np.ndarray, np.ndarray]:
    """(rgb (96, 128, 3) uint8, keypoints (9, 2) image px) of the Ketchup box at a fixed pose."""
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
    """Fit a lite network to :func:`box_scene`'s targets and save it as a dope-hope checkpoint."""
    torch.set_num_threads(1)
    rgb, kp = box_scene()
    model, cfg = fit_lite_model(rgb, kp, IMAGE_HW, steps)
    save_checkpoint(path, model, cfg, {"class_name": CLASS_NAME})
    return path
