"""The official DOPE maps -> poses decoder, re-implemented for timing (bench-only baseline).

A transcription of the decoding arithmetic (not the text) of NVlabs/Deep_Object_Pose,
``common/detector.py``: ``ObjectDetector.find_object_poses`` and ``ObjectDetector.find_objects``
(``run_sampling=False``, ``scale_factor=8``), with ``CuboidPNPSolver.solve_pnp``
(``src/dope/inference/cuboid_pnp_solver.py``, OpenCV >= 3) and the values of
``config/config_pose.yaml`` (:data:`OFFICIAL_CONFIG`). It keeps the official cost structure:
per channel a Gaussian smoothing and a 4-neighbour peak test on the whole map, a Python loop
over an 11x11 window per peak (weighted mean of the raw map, ``+ 0.4395``), and Python loops
over corner peaks x centroids reading the affinity one ``tensor.item()`` at a time, as the
official code does on the network's (CPU) tensors. Rules reproduced:

* a centroid peak whose raw value exceeds ``thresh_points`` starts an object;
* a corner peak (raw value >= ``thresh_points``) goes to the nearest centroid passing the
  angle test ``|v_aff / |v_aff| - u| < thresh_angle`` (v_aff read at the truncated peak
  position), replacing an earlier peak of that type only when nearer;
* an object with any of its nine points missing is dropped; the others go through
  ``cv2.solvePnP`` (SOLVEPNP_ITERATIVE for 6+ points, i.e. always here) with zero
  distortion, a pose behind the camera is mirrored (location negated, turned 180 deg about it).

Not reproduced: the debug prints, quaternion output (R is returned instead), sampling; and
one crash: on very noisy maps (negative raw values in the window) a weighted mean can land
outside the map, where the official code's affinity read raises IndexError (a negative index
within the map's size wraps, as there); such a peak is skipped here.
Used by ``bench/postprocess.py`` only; nothing in the package depends on it.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

#: ``config/config_pose.yaml`` (NVlabs/Deep_Object_Pose): decoding parameters.
OFFICIAL_CONFIG = {"thresh_angle": 0.5, "thresh_map": 0.01, "sigma": 3, "thresh_points": 0.1}
#: ``find_objects``: the weighted-mean window and the constant added to each peak position.
WINDOW = 11
OFFSET_DUE_TO_UPSAMPLING = 0.4395
SCALE_FACTOR = 8


def _peaks(belief: torch.Tensor, config: dict) -> list[list[tuple[float, float, float]]]:
    """Per channel, the (x, y, raw value) of every peak, map px (find_objects' first half)."""
    out = []
    half = WINDOW // 2
    for ch in range(belief.size()[0]):
        channel = belief[ch].clone()
        raw = channel.cpu().data.numpy()
        smooth = gaussian_filter(channel.cpu().data.numpy(), sigma=config["sigma"])
        # Shifted copies, zero-filled at the border: a peak is >= its four neighbours.
        shifted = [np.zeros(smooth.shape) for _ in range(4)]
        shifted[0][1:, :] = smooth[:-1, :]
        shifted[1][:-1, :] = smooth[1:, :]
        shifted[2][:, 1:] = smooth[:, :-1]
        shifted[3][:, :-1] = smooth[:, 1:]
        binary = np.logical_and.reduce([smooth >= s for s in shifted] + [smooth > config["thresh_map"]])
        cells = list(zip(np.nonzero(binary)[1], np.nonzero(binary)[0]))
        count = min(len(np.nonzero(binary)[1]), len(np.nonzero(binary)[0]))  # as the official counts them
        h, w = raw.shape
        found = []
        for x, y in cells[:count]:
            weights = np.zeros((WINDOW, WINDOW))
            ys = np.zeros((WINDOW, WINDOW))
            xs = np.zeros((WINDOW, WINDOW))
            for dy in range(-half, half + 1):
                for dx in range(-half, half + 1):
                    if y + dy < 0 or y + dy >= h or x + dx < 0 or x + dx >= w:
                        continue
                    ys[dx + half, dy + half] = y + dy
                    xs[dx + half, dy + half] = x + dx
                    weights[dx + half, dy + half] = raw[y + dy, x + dx]
            try:
                px = np.average(xs, weights=weights) + OFFSET_DUE_TO_UPSAMPLING
                py = np.average(ys, weights=weights) + OFFSET_DUE_TO_UPSAMPLING
            except ZeroDivisionError:  # weights summing to zero: the cell itself
                px, py = x + OFFSET_DUE_TO_UPSAMPLING, y + OFFSET_DUE_TO_UPSAMPLING
            found.append((px, py, raw[y, x]))
        out.append(found)
    return out


def find_objects(belief: torch.Tensor, affinity: torch.Tensor, config: dict = OFFICIAL_CONFIG,
                 scale_factor: int = SCALE_FACTOR) -> list[list]:
    """Objects as ``[centroid (x, y) map px, 8 corners (image px or None), 8 (angle, dist)]``.

    belief (9, h, w), affinity (16, h, w): torch tensors, as the network returns them."""
    all_peaks = _peaks(belief, config)
    objects = [[[px, py], [None] * 8, [None] * 8] for px, py, v in all_peaks[-1] if v > config["thresh_points"]]
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, peaks in enumerate(all_peaks[:-1]):
            for px, py, value in peaks:
                if value < config["thresh_points"]:
                    continue
                best, best_dist, best_angle = -1, 10000, 100
                h, w = affinity.shape[1:]
                if not (-h <= int(py) < h and -w <= int(px) < w):
                    continue  # the official affinity read would raise IndexError (module docstring)
                for i, obj in enumerate(objects):
                    cx, cy = obj[0]
                    ix, iy = int(px), int(py)
                    v = np.array([affinity[2 * k, iy, ix].data.item(),
                                  affinity[2 * k + 1, iy, ix].data.item()]) * 10
                    v = v / np.sqrt(v[0] * v[0] + v[1] * v[1])
                    u = np.array([cx, cy]) - np.array([px, py])
                    u = u / np.sqrt(u[0] * u[0] + u[1] * u[1])
                    angle = np.linalg.norm(u - v)
                    dist = np.linalg.norm(np.array([px, py]) - np.array([cx, cy]))
                    if angle < config["thresh_angle"] and (best_dist > 1000 or best_dist > dist):
                        best, best_angle, best_dist = i, angle, dist
                if best == -1:
                    continue
                obj = objects[best]
                if obj[1][k] is None or (best_angle < config["thresh_angle"] and best_dist < obj[2][k][1]):
                    obj[1][k] = (px * scale_factor, py * scale_factor)
                    obj[2][k] = (best_angle, best_dist)
    return objects


def solve_pnp(points: list, cuboid: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``CuboidPNPSolver.solve_pnp`` on nine (x, y) image points: (R (3, 3), t (3,)) or None."""
    img = np.array([p for p in points if p is not None], dtype=float)
    obj = np.array([c for c, p in zip(cuboid, points) if p is not None], dtype=float)
    if len(img) >= 6:
        flags = cv2.SOLVEPNP_ITERATIVE
    elif len(img) >= 4:
        flags, img, obj = cv2.SOLVEPNP_P3P, img[:4], obj[:4]
    else:
        return None
    dist = np.zeros((4, 1))
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flags)
    except cv2.error:
        return None
    if not ok:
        return None
    cv2.projectPoints(cuboid, rvec, tvec, K, dist)  # the official returns the projection too
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel().copy()
    if t[2] < 0:  # behind the camera: mirrored location, turned 180 deg about it
        t = -t
        R = Rotation.from_rotvec(np.pi * t / np.linalg.norm(t)).as_matrix() @ R
    return R, t


def find_object_poses(belief: torch.Tensor, affinity: torch.Tensor, cuboid: np.ndarray, K: np.ndarray,
                      config: dict = OFFICIAL_CONFIG, scale_factor: int = SCALE_FACTOR,
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses (R, t) of the complete objects in one image's maps, in ``find_objects`` order.

    cuboid: (9, 3) keypoints (8 corners, centroid) of the object, the points' order; K: (3, 3)
    intrinsics of the network input (image px = map px * ``scale_factor``)."""
    poses = []
    for centre, corners, _ in find_objects(belief, affinity, config, scale_factor):
        points = corners + [(centre[0] * scale_factor, centre[1] * scale_factor)]
        if None in points:
            continue  # "Incomplete cuboid detection. Skipping."
        pose = solve_pnp(points, cuboid, K)
        if pose is not None:
            poses.append(pose)
    return poses
