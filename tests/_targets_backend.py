"""Test helper (not a test module): a MapBackend whose "network" renders perfect maps.

``TargetsBackend`` knows a 3D scene (poses of one object class and the ORIGINAL image's K and
size). When the predictor hands it a batch, it finds the resized image inside the padding on
its own (the test images are one uniform colour, which normalizes to non-zero values, while
the predictor pads with exact zeros), derives the resize factors from that, projects the
cuboid keypoints with those factors and returns ``dope_hope.maps.targets.make_targets`` maps. So
the predictor's geometry bookkeeping (resize, padding, K scaling, legacy frame) is checked
against an independent derivation, and a correct pipeline must return the scene's poses.
"""
from __future__ import annotations

import numpy as np

from dope_hope.geometry import (
    KEYPOINT_ORDER,
    LEGACY_KEYPOINT_ORDER,
    LEGACY_TO_MESH,
    cuboid_keypoints,
    project_points,
)
from dope_hope.maps.targets import make_targets
from dope_hope.model.network import IMAGENET_MEAN, IMAGENET_STD


class TargetsBackend:
    """MapBackend protocol; ``poses`` are (R, t) of the frame the keypoints are defined in.

    frame "mesh": keypoints = cuboid_keypoints(size_m, center) under (R, t).
    frame "legacy": keypoints = cuboid_keypoints(|L|^T size_m) (legacy order) under (R, t),
    i.e. (R, t) is a legacy-frame pose, as the official HOPE networks see objects.
    """

    def __init__(self, class_name, size_m, poses, K, image_hw, frame="mesh", stride=8,
                 sigma=1.0, radius=1.5, center=None, input_hw=None):
        self.class_name = class_name
        self.size_m = np.asarray(size_m, dtype=np.float64)
        self.frame = frame
        self.keypoint_order = LEGACY_KEYPOINT_ORDER if frame == "legacy" else KEYPOINT_ORDER
        self.mean, self.std = tuple(IMAGENET_MEAN), tuple(IMAGENET_STD)
        self.input_hw = input_hw
        self.stride = stride
        self.poses = [(np.asarray(R, float), np.asarray(t, float)) for R, t in poses]
        self.K = np.asarray(K, dtype=np.float64)
        self.image_hw = tuple(image_hw)
        self.sigma, self.radius = sigma, radius
        self.center = np.zeros(3) if center is None else np.asarray(center, float)
        self.calls = []

    def network_keypoints(self, sx, sy):
        """(I, 9, 2) keypoints in network-input pixels for resize factors (sx, sy)."""
        if self.frame == "legacy":
            box = cuboid_keypoints(np.abs(LEGACY_TO_MESH).T @ self.size_m, LEGACY_TO_MESH.T @ self.center)
        else:
            box = cuboid_keypoints(self.size_m, self.center)
        uv = np.stack([project_points(box, self.K, R, t) for R, t in self.poses])
        return np.stack([sx * (uv[..., 0] + 0.5) - 0.5, sy * (uv[..., 1] + 0.5) - 0.5], -1)

    def run(self, batch):
        assert batch.dtype == np.float32 and batch.ndim == 4 and batch.shape[1] == 3
        N, _, Hp, Wp = batch.shape
        assert Hp % 8 == 0 and Wp % 8 == 0
        content = np.any(batch[0] != 0, axis=0)
        Hr = int(content.any(axis=1).sum())
        Wr = int(content.any(axis=0).sum())
        H, W = self.image_hw
        sx, sy = Wr / W, Hr / H
        self.calls.append({"padded": (Hp, Wp), "resized": (Hr, Wr)})
        kp = self.network_keypoints(sx, sy)
        belief, affinity = make_targets(kp, (Hp, Wp), self.stride, self.sigma, self.radius)
        return np.repeat(belief[None], N, 0), np.repeat(affinity[None], N, 0)


def demo_box_frame(root):
    """One 160x120 rendered frame of the demo box (no distractor, not cut off, 0.45-0.55 m),
    with depth, for a TargetsBackend to place: (frame folder, mesh path, GT R, GT t)."""
    from dope_hope.demo_object import write_demo_object
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.synth.generate import SynthJob
    from dope_hope.synth.to_disk import generate_dataset

    demo = write_demo_object(root / "mesh")
    cfg = {"target": {"count": [1, 1], "truncation_prob": 0.0, "distance_m": [0.45, 0.55]},
           "distractors": {"count": [0, 0], "occluder_prob": 0.0}}
    generate_dataset(root / "data", SynthJob(demo, size=(160, 120), config=cfg), 1, progress=False)
    (gt,) = read_dope_json(root / "data" / "000000.json").objects
    return root / "data", demo, gt.R, gt.t
