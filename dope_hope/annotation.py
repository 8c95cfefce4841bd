"""In-memory annotation types shared by every reader and writer (metres, mesh frame)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dope_hope.geometry import matrix_to_quaternion_xyzw


@dataclass
class ObjectAnnotation:
    """One object instance in one image.

    Attributes:
        class_name: object class, e.g. "Ketchup".
        R: (3, 3) rotation, model -> camera.
        t: (3,) translation, metres.
        projected_cuboid: (9, 2) pixel coordinates of the cuboid keypoints (documented order),
            or None when the file has none.
        visibility: visible fraction in [0, 1], or None.
        visible_pixels: visible pixel count when the file records one instead of a fraction
            (the official BlenderProc generator's ``visibility``), or None.
        bbox_xyxy: (4,) 2D box (x_min, y_min, x_max, y_max), pixels, or None.
        instance_id: id in the segmentation image, or None.
        keypoint_order: "dope-current" or "dope-legacy" (order of ``projected_cuboid``).
        stored_pose: (R (3, 3), t (3,) millimetres) exactly as a BOP file stores them (R not
            re-orthonormalized), or None; BOP19 scoring uses it to compute what the BOP
            toolkit computes.
    """

    class_name: str
    R: np.ndarray
    t: np.ndarray
    projected_cuboid: np.ndarray | None = None
    visibility: float | None = None
    visible_pixels: int | None = None
    bbox_xyxy: np.ndarray | None = None
    instance_id: int | None = None
    keypoint_order: str = "dope-current"
    stored_pose: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """(4,) scalar-last quaternion of R."""
        return matrix_to_quaternion_xyzw(self.R)


@dataclass
class FrameAnnotation:
    """The annotation of one image.

    Attributes:
        source: the annotation file.
        K: (3, 3) intrinsics or None (NDDS/FAT files carry none).
        width, height: image size in pixels, or None.
        objects: the instances.
        image_path, depth_path, seg_path: sibling files when they exist.
        depth_scale_m: metres per depth unit of ``depth_path`` (0.001 for uint16 millimetres).
        scene_id, im_id: BOP ids when the frame comes from a BOP split.
    """

    source: Path
    K: np.ndarray | None
    width: int | None
    height: int | None
    objects: list[ObjectAnnotation] = field(default_factory=list)
    image_path: Path | None = None
    depth_path: Path | None = None
    seg_path: Path | None = None
    depth_scale_m: float = 0.001
    scene_id: int | None = None
    im_id: int | None = None
