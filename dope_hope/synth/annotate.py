"""Annotations of a rendered frame: projected cuboids, visibility, 2D boxes.

Conventions of the generated annotation (also recorded in each JSON's ``synth`` block):

- ``projected_cuboid``: the 9 keypoints (documented order) of the mesh's AABB under the pose,
  projected with the frame's K (pixel centres at integer coordinates).
- ``visibility``: visible pixels / pixels of the same instance rendered alone on a canvas
  large enough for the whole object, so occlusion *and* truncation at the image border
  lower it. 0 for an instance hidden completely (kept in the file; readers filter).
- ``bbox_xyxy``: (x_min, y_min, x_max, y_max) of the instance's *visible* pixels, inclusive
  pixel-centre coordinates (a one-pixel object has x_min == x_max); None when invisible.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.geometry import KEYPOINT_ORDER, cuboid_keypoints, project_points
from dope_hope.symmetry.labels import canonical_rotation, corner_permutations
from dope_hope.symmetry.transforms import category_symmetries
from dope_hope.synth.scene import SceneSpec

if TYPE_CHECKING:  # render.py imports OpenGL; annotations need only the arrays
    from dope_hope.synth.render import RenderOutput


@dataclass(frozen=True)
class TargetBox:
    """What annotates one target object: its class and its cuboid (size (3,), centre (3,) in
    the mesh frame, metres)."""

    class_name: str
    size: np.ndarray
    center: np.ndarray


@dataclass
class InstanceStats:
    """Pixel statistics of one target instance."""

    instance_id: int
    px_count_visib: int
    px_count_all: int
    truncated: bool
    occluder_ids: list[int]


def mask_bbox(mask: np.ndarray) -> np.ndarray | None:
    """(4,) float (x_min, y_min, x_max, y_max) inclusive pixel coordinates of a mask, or None."""
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return np.array([cols[0], rows[0], cols[-1], rows[-1]], dtype=np.float64)


def annotate_frame(spec: SceneSpec, render: RenderOutput, boxes: Sequence[TargetBox],
                   source: Path | str = Path("frame.json")
                   ) -> tuple[FrameAnnotation, list[InstanceStats]]:
    """The FrameAnnotation (targets only, each with the class and cuboid of its target object
    ``boxes[obj.target_index]``) and per-instance pixel statistics."""
    keypoints = [cuboid_keypoints(b.size, b.center) for b in boxes]
    H, W = render.seg.shape
    objects, stats = [], []
    for obj in spec.targets:
        class_name, kp3 = boxes[obj.target_index].class_name, keypoints[obj.target_index]
        mask = render.seg == obj.seg_id
        visib = int(mask.sum())
        total = int(render.px_all.get(obj.seg_id, 0))
        uv = project_points(kp3, spec.K, obj.R, obj.t)
        corners = uv[:8]
        truncated = bool(np.any(corners < -0.5) or np.any(corners[:, 0] > W - 0.5) or
                         np.any(corners[:, 1] > H - 0.5))
        objects.append(ObjectAnnotation(
            class_name=class_name, R=obj.R.copy(), t=obj.t.copy(), projected_cuboid=uv,
            # Clamped: the alone pass can rasterize a pixel or two fewer than the scene pass
            # (seen: 1.00004), and readers require a fraction in [0, 1].
            visibility=min(1.0, float(visib / total)) if total > 0 else 0.0, bbox_xyxy=mask_bbox(mask),
            instance_id=obj.seg_id, keypoint_order=KEYPOINT_ORDER))
        occluders = sorted(int(o.seg_id) for o in spec.objects if o.occluder_of == obj.seg_id)
        stats.append(InstanceStats(obj.seg_id, visib, total, truncated, occluders))
    frame = FrameAnnotation(source=Path(source), K=spec.K.copy(), width=spec.width,
                            height=spec.height, objects=objects, depth_scale_m=0.001)
    return frame, stats


def canonical_pose_labels(spec: SceneSpec, category: str, cuboid_size: np.ndarray) -> SceneSpec:
    """The scene with each target's rotation replaced by its symmetric equivalent ``R S`` that
    :mod:`dope_hope.symmetry.labels` makes canonical for a HOPE ``category`` (what
    ``targets.symmetry=auto`` does to a HOPE object of that category), for annotation only:
    the model frame must be centred on the cuboid (procedural objects are)."""
    rotations, _ = corner_permutations(cuboid_size, category_symmetries(category, step_deg=90.0))
    objects = [replace(o, R=canonical_rotation(o.R, o.t, rotations)) if o.role == "target" else o
               for o in spec.objects]
    return replace(spec, objects=objects)
