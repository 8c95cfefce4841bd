"""Isaac ROS DOPE (``isaac_ros_dope``) per release: vertex order, launch arguments, decoder.

What a release of NVIDIA-ISAAC-ROS/isaac_ros_pose_estimation does with an exported
``(1, 25, H/8, W/8)`` output. Sources: ``isaac_ros_gxf_extensions/gxf_isaac_dope/gxf/dope/
dope_decoder.cpp`` (3.0.0 at 19059d0d, 3.2.0 at 320c75d6, 4.0.0 at c97c42af),
``isaac_ros_dope/gxf/dope/dope_decoder.cpp`` (2.x at d31cf362), the launch files named below
and ``isaac_ros_dope/config/dope_config.yaml``. No 3.1 source was at hand: 3.1 is taken to be
3.0's decoder (the decoder file has no other version between 3.0 and 3.2).

- **Cuboid vertex order** (``CuboidVertices`` of the DOPE decoder; :func:`cuboid_vertices`).
  Up to 3.1 it is :data:`dope_hope.geometry.CUBOID_CORNER_SIGNS` (``right = +x/2``,
  ``top = -y/2``). Since 3.2 (gxf_isaac_dope ``dope_decoder.cpp``, package 3.2.0 and 4.0.0,
  and the 2026 ROS-node decoder) ``right = -x/2``, ``top = +y/2``: the same order turned 180
  degrees about z. Belief channel k is vertex k, channels ``9 + 2k, 10 + 2k`` its affinity
  field, channel 8 the centroid. :func:`channel_order` permutes the exported output
  (:func:`dope_hope.model.onnx_contract.output_order`) so that the decoder's PnP returns the
  **mesh-frame** pose (for legacy-frame models too) when the ``dimensions`` are the mesh-frame
  extents in cm (:func:`dope_config_entry`).
- **Decoder arithmetic** (:func:`decode`, a transcription used by tests and benches): blur
  sigma 3 (``BORDER_REFLECT``), 3x3 non-plateau maxima above 0.01, weighted mean of the raw
  map around each peak, ``(peak + 0.4395) * 8`` image px, corner-to-centroid association by
  the affinity angle (< 0.5) and distance, ``cv::solvePnP`` on the vertices, translation / 100.
  2.x: an 11x11 window, raw peak >= 0.01, >= 6 points (centroid + 5 corners),
  ``SOLVEPNP_EPNP``. 3.0 and 3.1: a 5x5 window indexed (x, y) as (row, col) (on clean maps it
  reads zeros and falls back to the integer peak; on a network's noisy maps it averages the
  noise at the transposed position), ``SOLVEPNP_ITERATIVE``, otherwise as 2.x. Since 3.2: the
  11x11 window again, raw peak >= ``map_peak_threshold`` (node default 0.1), all 9 points,
  ``SOLVEPNP_EPNP``, then ``R * Rz(c) Ry(b) Rx(a)`` with the ``rotation_*_axis`` parameters
  (radians, default 0).
- **Launch defaults** (:class:`IsaacRosRelease`): up to 3.1 ``isaac_ros_dope_tensor_rt.launch.py``
  (as in 3.0.0: 640x480, encoder mean = std = 0.5); since 3.2 ``isaac_ros_dope_core.launch.py``
  (launch fragment ``dope``, 3.2.0: 1280x720, ImageNet mean/std, ``map_peak_threshold`` 0.1).
  The exported graph's tensor names (``input`` -> ``output``) are the binding names of every
  release. :func:`launch_arguments` lists every argument with the value an export needs, so
  a default that differs in some release does not matter.
"""
from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.errors import ConfigError
from dope_hope.geometry import CENTROID_INDEX, CUBOID_CORNER_SIGNS, LEGACY_TO_MESH, NUM_KEYPOINTS

# numpy, OpenCV, scipy and geometry are imported inside the functions: `dope-hope export` reads
# ISAAC_ROS_CURRENT from this module to build its --help, which must not pay for them.

if TYPE_CHECKING:
    import numpy as np

# numpy and dope_hope.geometry (scipy) are imported inside the functions: the CLI imports this
# module for ISAAC_ROS_CURRENT when it builds its parser, and must stay quick to start.

#: The newest release checked (isaac_ros_dope package.xml 4.0.0); the default target. Later
#: versions are refused: their decoder's vertex order is unknown.
ISAAC_ROS_CURRENT = "4.0"
NEWEST = (4, 0)
#: First release whose ``CuboidVertices`` is turned 180 degrees about z.
FLIPPED_SINCE = (3, 2)
#: Oldest release accepted (0.x "DP" releases hard-coded 60x80 maps in a ROS node).
OLDEST = (2, 0)
#: The decoder's constants (same in every release checked).
MAP_SCALE = 8.0
PEAK_OFFSET = 0.4395
BLUR_SIGMA = 3.0
BLURRED_PEAK_THRESHOLD = 0.01
MIN_WEIGHT_SUM = 1e-6
#: Image encoder normalizations (mean, std) by name.
ENCODERS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "half": ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
    "imagenet": ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225)),
}
_TENSOR_ARGS = {
    "input_tensor_names": '["input_tensor"]',
    "input_binding_names": '["input"]',
    "input_tensor_formats": '["nitros_tensor_list_nchw_rgb_f32"]',
    "output_tensor_names": '["output"]',
    "output_binding_names": '["output"]',
    "output_tensor_formats": '["nitros_tensor_list_nhwc_rgb_f32"]',
    "tensorrt_verbose": "False",
}
#: Launch arguments in declaration order with their defaults (strings, as in the files).
_LAUNCH_UP_TO_3_1 = {
    "input_image_width": "1920", "input_image_height": "1080",
    "network_image_width": "640", "network_image_height": "480",
    "encoder_image_mean": "[0.5, 0.5, 0.5]", "encoder_image_stddev": "[0.5, 0.5, 0.5]",
    "model_file_path": "<package>/test/models/dope_ketchup_pol.onnx",
    "engine_file_path": "/tmp/trt_engine.plan", **_TENSOR_ARGS,
    "object_name": "Ketchup", "force_engine_update": "False",
}
_LAUNCH_SINCE_3_2 = {
    "network_image_width": "1280", "network_image_height": "720",
    "encoder_image_mean": "[0.485, 0.456, 0.406]", "encoder_image_stddev": "[0.229, 0.224, 0.225]",
    "model_file_path": "", "engine_file_path": "", **_TENSOR_ARGS,
    "object_name": "Ketchup", "map_peak_threshold": "0.1", "force_engine_update": "False",
    "enable_tf_publishing": "False",
}


@dataclass(frozen=True)
class IsaacRosRelease:
    """One Isaac ROS release as its DOPE decoder and launch file see an exported model.

    version: "MAJOR.MINOR[.PATCH]". flipped: vertex order turned 180 deg about z (3.2+).
    launch_file: the launch file whose arguments :func:`launch_arguments` lists.
    launch_defaults: its arguments in declaration order with their default values.
    encoder: the default image normalization ("half" | "imagenet").
    window: the decoder's weighted-mean window (5: 3.0-3.1, transposed indexing; 11). min_points:
    keypoints PnP needs (centroid included). pnp: "iterative" | "epnp".
    map_peak_threshold: the raw belief a peak needs (node default).
    """

    version: str
    flipped: bool
    launch_file: str
    launch_defaults: dict[str, str] = field(repr=False)
    encoder: str
    window: int
    min_points: int
    pnp: str
    map_peak_threshold: float


def isaac_ros_release(version: str = ISAAC_ROS_CURRENT) -> IsaacRosRelease:
    """The :class:`IsaacRosRelease` of ``version`` ("3.1", "4.0", ...); ConfigError if unusable."""
    m = re.fullmatch(r"(\d+)\.(\d+)(?:\.\d+)?", str(version).strip())
    if not m:
        raise ConfigError(f"--isaac-ros-version must look like 3.1 or 4.0, got {version!r}")
    major_minor = (int(m.group(1)), int(m.group(2)))
    if major_minor < OLDEST:
        raise ConfigError(f"--isaac-ros-version {version}: releases before {OLDEST[0]}.{OLDEST[1]} "
                          "(hard-coded 60x80 maps) are not supported")
    if major_minor > NEWEST:
        raise ConfigError(f"--isaac-ros-version {version}: newer than the newest known release "
                          f"{ISAAC_ROS_CURRENT} (its decoder's cuboid vertex order is unchecked); "
                          f"use {ISAAC_ROS_CURRENT} or earlier")
    version = str(version).strip()
    if major_minor >= FLIPPED_SINCE:
        return IsaacRosRelease(version, True, "isaac_ros_dope_core.launch.py",
                               dict(_LAUNCH_SINCE_3_2), "imagenet", 11, 9, "epnp", 0.1)
    window, pnp = (5, "iterative") if major_minor >= (3, 0) else (11, "epnp")
    return IsaacRosRelease(version, False, "isaac_ros_dope_tensor_rt.launch.py",
                           dict(_LAUNCH_UP_TO_3_1), "half", window, 6, pnp, 0.01)


# ----------------------------------------------------------------------------- vertex order
def cuboid_vertices(dims: Sequence[float], release: IsaacRosRelease) -> np.ndarray:
    """(3, 9) ``CuboidVertices(ext)`` of ``release``: columns = vertices 0..7, centroid (units of dims)."""
    x, y, z = (float(v) for v in dims)
    if release.flipped:
        right, left, bottom, top = -x * 0.5, x * 0.5, -y * 0.5, y * 0.5
    else:
        right, left, bottom, top = x * 0.5, -x * 0.5, y * 0.5, -y * 0.5
    front, rear = z * 0.5, -z * 0.5
    return np.array([
        [right, left, left, right, right, left, left, right, 0.0],
        [top, top, bottom, bottom, top, top, bottom, bottom, 0.0],
        [front, front, front, front, rear, rear, rear, rear, 0.0],
    ])


def channel_order(frame: str, release: IsaacRosRelease) -> np.ndarray:
    """(9,) int: Isaac belief channel k shows the model's channel ``order[k]`` (centroid last).

    The model's corner j lies at mesh-frame signs ``CUBOID_CORNER_SIGNS[j]`` (frame "mesh") or
    ``LEGACY_TO_MESH @ CUBOID_CORNER_SIGNS[j]`` (frame "legacy"); Isaac's vertex k at the signs
    of :func:`cuboid_vertices`. Matching them makes PnP on the mesh-frame extents return the
    mesh-frame pose.
    """
    if frame not in ("mesh", "legacy"):
        raise ConfigError(f"object frame must be 'mesh' or 'legacy', got {frame!r}")
    ours = CUBOID_CORNER_SIGNS if frame == "mesh" else CUBOID_CORNER_SIGNS @ LEGACY_TO_MESH.T
    theirs = np.sign(cuboid_vertices((2.0, 2.0, 2.0), release).T[:CENTROID_INDEX])
    order = [int(np.flatnonzero(np.all(ours == s, axis=1))[0]) for s in theirs]
    return np.array(order + [CENTROID_INDEX])


# ----------------------------------------------------------------------------- launch
def dope_config_entry(class_name: str, size_m: Sequence[float]) -> str:
    """The ``dimensions`` line of ``config/dope_config.yaml``: mesh-frame x, y, z extents, cm."""
    dims = [round(float(v) * 100.0, 4) for v in size_m]
    return f'"{class_name}": [{", ".join(f"{v:g}" for v in dims)}]'


def launch_arguments(release: IsaacRosRelease, model_path: str | Path, input_hw: Sequence[int],
                     encoder: str, object_name: str) -> dict[str, str]:
    """Every argument of the release's launch file with the value this export needs.

    Values as on a ``ros2 launch`` command line; arguments this export does not constrain
    (camera size, formats, thresholds) keep their defaults.
    """
    mean, std = ENCODERS[encoder]
    model_path = Path(model_path).resolve()
    ours = {
        "network_image_width": str(int(input_hw[1])), "network_image_height": str(int(input_hw[0])),
        "encoder_image_mean": json.dumps(list(mean)), "encoder_image_stddev": json.dumps(list(std)),
        "model_file_path": str(model_path), "engine_file_path": str(model_path.with_suffix(".plan")),
        "input_binding_names": '["input"]', "output_binding_names": '["output"]',
        "object_name": str(object_name),
    }
    return {k: ours.get(k, v) for k, v in release.launch_defaults.items()}


# ----------------------------------------------------------------------------- decoder
def _isolate_maxima(src: np.ndarray) -> np.ndarray:
    dil = cv2.dilate(src, None)
    ero = cv2.erode(src, None)
    return (src >= dil) & (src > ero)


def _weighted_peak(image: np.ndarray, px: int, py: int, release: IsaacRosRelease) -> tuple[float, float]:
    """The decoder's weighted mean around peak (x, y) = (px, py), float32 as in C++; map px."""
    rows, cols = image.shape
    transposed = release.window == 5  # 3.0-3.1: row = x + ii, col = y + jj (x and y swapped)
    half = release.window // 2
    ws = sr = sc = np.float32(0.0)
    for ii in range(-half, half + 1):
        for jj in range(-half, half + 1):
            row, col = (px + ii, py + jj) if transposed else (py + ii, px + jj)
            if col < 0 or col >= cols or row < 0 or row >= rows:
                continue
            w = image[row, col]
            ws = np.float32(ws + w)
            sr = np.float32(sr + np.float32(row) * w)
            sc = np.float32(sc + np.float32(col) * w)
    sx, sy = (sr, sc) if transposed else (sc, sr)  # peak_sum[0] is x in the C++
    off = np.float32(PEAK_OFFSET)
    if abs(float(ws)) < MIN_WEIGHT_SUM:
        return float(np.float32(px) + off), float(np.float32(py) + off)
    return float(np.float32(sx / ws) + off), float(np.float32(sy / ws) + off)


def find_objects(maps: np.ndarray, release: IsaacRosRelease, map_peak_threshold: float | None = None,
                 angle_threshold: float = 0.5) -> list[tuple[list[int], np.ndarray]]:
    """``FindObjects``: (25, h, w) output -> [(vertex indices, (N, 2) image px)] per object.

    Indices are the valid corners in increasing order, then 8 (centroid); objects with fewer
    than ``release.min_points`` are dropped, as the decoder does.
    """
    maps = np.ascontiguousarray(maps, dtype=np.float32)
    if maps.ndim != 3 or maps.shape[0] != 25:
        raise ValueError(f"expected the (25, h, w) Isaac ROS output, got {maps.shape}")
    thr = release.map_peak_threshold if map_peak_threshold is None else float(map_peak_threshold)
    h, w = maps.shape[1:]
    all_peaks: list[tuple[float, float]] = []
    channel_peaks: list[list[int]] = [[] for _ in range(NUM_KEYPOINTS)]
    for chan in range(NUM_KEYPOINTS):
        image = maps[chan]
        blurred = cv2.GaussianBlur(image, (0, 0), BLUR_SIGMA, sigmaY=BLUR_SIGMA, borderType=cv2.BORDER_REFLECT)
        mask = _isolate_maxima(blurred)
        found = cv2.findNonZero(mask.astype(np.uint8))
        for px, py in ([] if found is None else found.reshape(-1, 2).tolist()):
            if not blurred[py, px] > BLURRED_PEAK_THRESHOLD:
                continue
            if image[py, px] >= thr:
                channel_peaks[chan].append(len(all_peaks))
                all_peaks.append(_weighted_peak(image, px, py, release))
    peaks = np.asarray(all_peaks, dtype=np.float32).reshape(-1, 2)
    centers = channel_peaks[CENTROID_INDEX]
    corners = [[-1] * CENTROID_INDEX for _ in centers]
    best_d = [[np.inf] * CENTROID_INDEX for _ in centers]
    for chan in range(CENTROID_INDEX):
        for p in channel_peaks[chan]:
            best_idx, best_dist, best_angle = -1, np.inf, np.inf
            point = peaks[p]
            # Eigen's int cast truncates; clipped here where C++ would read out of bounds.
            xi = min(max(int(point[0]), 0), w - 1)
            yi = min(max(int(point[1]), 0), h - 1)
            v_aff = np.array([maps[NUM_KEYPOINTS + 2 * chan, yi, xi],
                              maps[NUM_KEYPOINTS + 2 * chan + 1, yi, xi]], dtype=np.float32)
            n = np.linalg.norm(v_aff)
            if n > 0:
                v_aff = v_aff / n
            for j, c in enumerate(centers):
                d = peaks[c] - point
                dist = float(np.linalg.norm(d))
                v_center = d / dist if dist > 0 else d
                angle = float(np.linalg.norm(v_center - v_aff))
                if angle < angle_threshold and dist < best_dist:
                    best_idx, best_dist, best_angle = j, dist, angle
            if best_idx < 0:
                continue
            if corners[best_idx][chan] == -1 or (best_angle < angle_threshold
                                                  and best_dist < best_d[best_idx][chan]):
                corners[best_idx][chan] = p
                best_d[best_idx][chan] = best_dist
    out = []
    for c, obj in zip(centers, corners):
        valid = [k for k in range(CENTROID_INDEX) if obj[k] != -1] + [CENTROID_INDEX]
        if len(valid) < release.min_points:
            continue
        ids = [obj[k] for k in valid[:-1]] + [c]
        out.append((valid, peaks[ids] * np.float32(MAP_SCALE)))
    return out


def _euler_step(angle: float, axis: int) -> np.ndarray:
    return Rotation.from_rotvec(np.eye(3)[axis] * float(angle)).as_matrix()


def extract_pose(valid: Sequence[int], image_points: np.ndarray, dims_cm: Sequence[float], K: np.ndarray,
                 release: IsaacRosRelease, rotation_xyz: Sequence[float] = (0.0, 0.0, 0.0)):
    """``ExtractPose``: PnP on the release's vertices -> (R (3, 3), t (3,) metres) or None."""
    pts3 = cuboid_vertices(dims_cm, release)[:, list(valid)].T.astype(np.float64)
    pts2 = np.asarray(image_points, dtype=np.float32).astype(np.float64)
    flag = cv2.SOLVEPNP_EPNP if release.pnp == "epnp" else cv2.SOLVEPNP_ITERATIVE
    ok, rvec, tvec = cv2.solvePnP(pts3, pts2, np.asarray(K, np.float64), np.zeros(4), flags=flag)
    if not ok:
        return None
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    if release.flipped:  # composed_rotation = Rz * Ry * Rx, applied on the right
        a, b, c = rotation_xyz
        R = R @ (_euler_step(c, 2) @ _euler_step(b, 1) @ _euler_step(a, 0))
    if t[2] < 0:  # Pose3d::inverse(): negated translation, inverted rotation
        t, R = -t, R.T
    return R, t / 100.0


def decode(output: np.ndarray, K: np.ndarray, dims_cm: Sequence[float], release: IsaacRosRelease,
           map_peak_threshold: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The poses Isaac ROS ``release`` publishes for one (1, 25, h, w) or (25, h, w) output.

    K: (3, 3) intrinsics of the network input image. dims_cm: the ``dimensions`` entry.
    Returns [(R (3, 3), t (3,) metres)], one per object, in the decoder's order.
    """
    maps = np.asarray(output)
    maps = maps[0] if maps.ndim == 4 else maps
    poses = []
    for valid, pts in find_objects(maps, release, map_peak_threshold):
        pose = extract_pose(valid, pts, dims_cm, K, release)
        if pose is not None:
            poses.append(pose)
    return poses
