"""Training targets: belief maps and affinity fields from projected cuboid keypoints.

Encoding rules (``decode`` inverts them with the same :mod:`dope_hope.maps.grid` convention):

* **Belief map** ``k`` holds, per instance, an *untruncated* isotropic Gaussian
  ``exp(-d^2 / (2 sigma^2))`` centred on keypoint ``k``'s continuous map position
  ``mapgrid.image_to_map(uv, stride)`` and evaluated at the map cell centres (integer map
  coordinates). Instances are combined with a per-cell maximum, so each peak stays 1 at its
  keypoint. Keypoints outside the image are encoded like the others: their peak lies outside
  the map but their tails reach into it (the network learns "the corner is just off-screen").
  Rows with NaN are absent and contribute nothing.
* **Affinity field** of corner ``k`` (channels ``2k`` = x, ``2k+1`` = y): in every cell whose
  centre lies within ``radius`` map pixels of corner ``k``, the unit vector *from that cell*
  towards its instance's centroid (keypoint 8). Where disks of several instances overlap the
  vectors are summed and the sum renormalized to unit length (the official DOPE rule, which
  averages pairwise and renormalizes); a cell where they cancel exactly stays zero. An
  instance whose centroid is absent (NaN) contributes no affinity.

Official DOPE choices mirrored here (NVlabs/Deep_Object_Pose ``train/train.py`` and
``train/utils.py``: ``CreateBeliefMap`` / ``GenerateMapAffinity`` / ``getAfinityCenter``):

* belief Gaussians drawn directly at the 50-px output with ``sigma = 0.5`` map px
  (``output_size = 50; opt.sigma = 0.5``); the 2018 ``scripts/train.py`` drew them with
  ``--sigma`` (default 4, which overrides the dataset class's default of 16) on the ~400-px
  image and resized the maps by 1/8: the same 4 image px. DOPE truncates the
  Gaussian at +-2 sigma and *drops* a keypoint whose window crosses the border; we keep the
  untruncated Gaussian and off-image keypoints (their tails), so the sub-pixel fit in
  ``decode`` is exact on clean targets and truncated objects still get supervision.
* affinity disks of radius 1 map px at the 50-px output, combined by sum + renormalize. DOPE
  draws one constant vector (corner -> centroid) over the whole disk; we use the per-cell
  direction (cell -> centroid), which is exactly what ``decode`` compares against at a peak
  cell. For radius 1 and a box more than a few cells wide the two differ by a few degrees.

Sigma and radius per head: both are in *map* pixels, so keep their *image* footprint fixed
and divide by the stride (:func:`head_defaults`): ``sigma = 4 px / stride`` and
``radius = 8 px / stride``, i.e. (0.5, 1) for DOPE-DR-50 (stride 8, the official values) and
(4, 8) for DOPE-DR-400 (stride 1). The configs (section ``targets``) override them
(``dope_dr_50.yaml``: sigma 2 = 16 image px; ``dope_dr_400.yaml``: sigma 8): a larger sigma
gives denser supervision and more support for the sub-pixel fit, but merges the peaks of
same-type keypoints of nearby instances sooner (decode separates peaks about
``2 * sqrt(sigma^2 + smooth_sigma^2)`` map px apart).
"""
from __future__ import annotations

import numpy as np

from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS
from dope_hope.maps.grid import image_to_map, map_size

#: Official DOPE footprint in *image* pixels: sigma 0.5 and radius 1 map px at stride 8.
DOPE_SIGMA_IMAGE_PX = 4.0
DOPE_RADIUS_IMAGE_PX = 8.0


def head_defaults(stride: int) -> tuple[float, float]:
    """(sigma, radius) in map pixels for a head of this stride, official DOPE footprint."""
    return DOPE_SIGMA_IMAGE_PX / stride, DOPE_RADIUS_IMAGE_PX / stride


def _as_keypoints(keypoints: np.ndarray) -> np.ndarray:
    """Validate and return keypoints as (I, 9, 2) float64 (an empty array is allowed)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.size == 0:
        return np.zeros((0, NUM_KEYPOINTS, 2))
    if kp.ndim == 2:
        kp = kp[None]
    if kp.ndim != 3 or kp.shape[1:] != (NUM_KEYPOINTS, 2):
        raise ValueError(f"keypoints must be (I, {NUM_KEYPOINTS}, 2), got {kp.shape}")
    return kp


def belief_maps(
    keypoints: np.ndarray, map_hw: tuple[int, int], stride: int, sigma: float
) -> np.ndarray:
    """Gaussian belief maps.

    Args:
        keypoints: (I, 9, 2) image pixel coordinates (u, v); NaN rows are absent.
        map_hw: (h, w) of the maps.
        stride: image pixels per map cell (8 or 1).
        sigma: Gaussian standard deviation, map pixels.

    Returns:
        (9, h, w) float32 in [0, 1]; the per-cell maximum over instances.
    """
    kp = _as_keypoints(keypoints)
    h, w = int(map_hw[0]), int(map_hw[1])
    out = np.zeros((NUM_KEYPOINTS, h, w), dtype=np.float32)
    if kp.shape[0] == 0:
        return out
    mu = image_to_map(kp, stride)  # (I, 9, 2) continuous map coords
    xs = np.arange(w, dtype=np.float64)
    ys = np.arange(h, dtype=np.float64)
    inv = 1.0 / (2.0 * float(sigma) ** 2)
    for inst in mu:  # loop over instances only; the Gaussian is separable
        present = np.all(np.isfinite(inst), axis=1)
        if not present.any():
            continue
        gx = np.exp(-((xs[None, :] - inst[:, 0:1]) ** 2) * inv)  # (9, w)
        gy = np.exp(-((ys[None, :] - inst[:, 1:2]) ** 2) * inv)  # (9, h)
        g = (gy[:, :, None] * gx[:, None, :]).astype(np.float32)  # (9, h, w)
        g[~present] = 0.0
        np.maximum(out, g, out=out)
    return out


def affinity_fields(
    keypoints: np.ndarray, map_hw: tuple[int, int], stride: int, radius: float
) -> np.ndarray:
    """Corner-to-centroid unit vector fields.

    Args:
        keypoints: (I, 9, 2) image pixel coordinates; NaN rows are absent.
        map_hw: (h, w) of the maps.
        stride: image pixels per map cell.
        radius: disk radius around each corner, map pixels (cells whose centre lies within it).

    Returns:
        (16, h, w) float32; channels 2k, 2k+1 = x, y of the unit vector from the cell towards
        its instance's centroid near corner k, zero elsewhere; overlaps are summed and
        renormalized.
    """
    kp = _as_keypoints(keypoints)
    h, w = int(map_hw[0]), int(map_hw[1])
    acc = np.zeros((CENTROID_INDEX, 2, h, w), dtype=np.float64)
    if kp.shape[0] == 0:
        return acc.reshape(2 * CENTROID_INDEX, h, w).astype(np.float32)
    mu = image_to_map(kp, stride)
    r = float(radius)
    span = int(np.ceil(r))
    corners, centroids = mu[:, :CENTROID_INDEX], mu[:, CENTROID_INDEX]  # (I, 8, 2), (I, 2)
    present = np.all(np.isfinite(corners), axis=2) & np.all(np.isfinite(centroids), axis=1)[:, None]
    inst, k = np.nonzero(present)  # (M,) each: instance-major, the order the sums run in
    if len(inst):
        # Every corner's cells at once: a (2 span + 2)^2 window from floor(p) - span holds its disk.
        p, c = corners[inst, k], centroids[inst]  # (M, 2) each
        off = np.arange(-span, span + 2, dtype=np.float64)
        xx = np.floor(p[:, 0])[:, None, None] + off[None, None, :]  # (M, 1, S)
        yy = np.floor(p[:, 1])[:, None, None] + off[None, :, None]  # (M, S, 1)
        xx, yy = np.broadcast_arrays(xx, yy)  # (M, S, S)
        vx, vy = c[:, 0, None, None] - xx, c[:, 1, None, None] - yy
        norm = np.hypot(vx, vy)
        keep = (((xx - p[:, 0, None, None]) ** 2 + (yy - p[:, 1, None, None]) ** 2 <= r * r)
                & (xx >= 0) & (xx <= w - 1) & (yy >= 0) & (yy <= h - 1) & (norm > 1e-9))
        m = np.nonzero(keep)[0]
        cell = yy[keep].astype(np.int64) * w + xx[keep].astype(np.int64)
        flat = acc.reshape(CENTROID_INDEX, 2, h * w)
        np.add.at(flat, (k[m], 0, cell), vx[keep] / norm[keep])
        np.add.at(flat, (k[m], 1, cell), vy[keep] / norm[keep])
    norm = np.hypot(acc[:, 0], acc[:, 1])[:, None]  # (8, 1, h, w)
    acc = np.where(norm > 1e-9, acc / np.where(norm > 1e-9, norm, 1.0), 0.0)
    return acc.reshape(2 * CENTROID_INDEX, h, w).astype(np.float32)


def make_targets(
    keypoints: np.ndarray,
    image_hw: tuple[int, int],
    stride: int,
    sigma: float | None = None,
    radius: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Belief maps and affinity fields for an image of (H, W) at the given head stride.

    Args:
        keypoints: (I, 9, 2) image pixels, NaN = absent.
        image_hw: (H, W) of the network input image.
        stride: 8 (50-px head) or 1 (400-px head).
        sigma, radius: map pixels; None = :func:`head_defaults` for this stride.

    Returns:
        belief (9, h, w) float32, affinity (16, h, w) float32 with (h, w) =
        ``mapgrid.map_size(image_hw, stride)``.
    """
    hw = map_size(image_hw, stride)
    d_sigma, d_radius = head_defaults(stride)
    sigma = d_sigma if sigma is None else sigma
    radius = d_radius if radius is None else radius
    return (
        belief_maps(keypoints, hw, stride, sigma),
        affinity_fields(keypoints, hw, stride, radius),
    )
