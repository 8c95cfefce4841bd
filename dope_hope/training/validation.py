"""Validation keypoint accuracy: decoded keypoints within ``radius_px`` of the ground truth.

The fraction of visible GT keypoints with a prediction of the same keypoint index within
``val_radius_px`` (5 px at input scale).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dope_hope.geometry import NUM_KEYPOINTS
from dope_hope.maps.decode import DecodeSettings, decode_maps, decoder_peaks
from dope_hope.maps.grid import map_to_image
from dope_hope.model.info import group_channels


# =============================================================================== metrics
def keypoint_hits(predicted: Sequence[np.ndarray], gt: np.ndarray, radius_px: float) -> tuple[int, int]:
    """Count visible GT keypoints that a prediction of the same index finds.

    Each predicted point of keypoint index k is matched to the nearest GT instance's keypoint
    k; a GT keypoint is found when a point matched to it lies within ``radius_px``.

    Args:
        predicted: 9 arrays (m_k, 2) of predicted image pixels for keypoints 0..8.
        gt: (I, 9, 2) GT image pixels, NaN = absent / outside the image.
        radius_px: hit radius, input-image pixels.

    Returns:
        (found, visible).
    """
    found = visible = 0
    for k in range(NUM_KEYPOINTS):
        g = gt[:, k]
        g = g[np.all(np.isfinite(g), axis=1)]
        visible += len(g)
        p = np.asarray(predicted[k], dtype=np.float64).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(g) == 0 or len(p) == 0:
            continue
        d = np.linalg.norm(p[:, None, :] - g[None, :, :], axis=2)  # (m, I)
        nearest = d.argmin(1)
        hit = np.zeros(len(g), bool)
        close = d[np.arange(len(p)), nearest] <= radius_px
        hit[nearest[close]] = True
        found += int(hit.sum())
    return found, visible


def validation_hits(belief: np.ndarray, affinity: np.ndarray, gt: np.ndarray, stride: int,
                    radius_px: float, threshold: float) -> tuple[int, int, int, int]:
    """Keypoint hits of one image, two ways: (found, visible) for the belief peaks and for the
    instances of :func:`dope_hope.maps.decode.decode_maps`, both found as inference finds them
    (the decoder's settings, :class:`~dope_hope.maps.decode.DecodeSettings`, at ``threshold``).

    Both keep as many predictions as the image has GT instances with a visible keypoint (the
    strongest peaks per keypoint index; the best-scoring decoded instances), so that a map
    full of spurious peaks cannot score by chance.

    Args:
        belief: (9, h, w); affinity: (16, h, w); gt: (I, 9, 2) input pixels, NaN = not visible.
        stride: map stride; radius_px: hit radius, input pixels; threshold: peak threshold.
    """
    n_inst = max(1, int(np.any(np.all(np.isfinite(gt), axis=2), axis=1).sum()))
    settings = DecodeSettings(threshold=threshold)  # the rest as inference decodes (noise floor included)
    peaks = decoder_peaks(belief, settings)
    pred = []
    for k in range(NUM_KEYPOINTS):
        sel = np.flatnonzero(peaks.channel == k)
        sel = sel[np.argsort(-peaks.score[sel])[:n_inst]]
        pred.append(map_to_image(peaks.xy[sel], stride))
    found, visible = keypoint_hits(pred, gt, radius_px)
    instances = decode_maps(belief, affinity, stride, settings, peaks=peaks)[:n_inst]
    pred_d = [np.array([inst.keypoints[k] for inst in instances]).reshape(-1, 2) for k in range(NUM_KEYPOINTS)]
    found_d, visible_d = keypoint_hits(pred_d, gt, radius_px)
    return found, visible, found_d, visible_d


def object_hits(belief: np.ndarray, affinity: np.ndarray, gt: np.ndarray, classes: np.ndarray,
                num_objects: int, stride: int, radius_px: float, threshold: float) -> np.ndarray:
    """:func:`validation_hits` of each object's belief/affinity group against its own instances.

    Args:
        belief: (9N, h, w); affinity: (16N, h, w); gt: (I, 9, 2) input pixels (NaN = not
            visible); classes: (I,) object index of each gt row (-1 = padding).

    Returns:
        (N, 4) int: per object (found, visible, found_decoded, visible_decoded).
    """
    maps = np.concatenate([belief, affinity], axis=0)
    out = np.zeros((num_objects, 4), np.int64)
    for k in range(num_objects):
        mine = gt[classes == k]
        if not np.isfinite(mine).any():
            continue  # nothing of this object to find in this image
        group = maps[group_channels(k, num_objects)]
        out[k] = validation_hits(group[:NUM_KEYPOINTS], group[NUM_KEYPOINTS:], mine, stride, radius_px, threshold)
    return out


def per_object_accuracy(names: Sequence[str], hits: Sequence[Sequence[float]]) -> dict[str, float]:
    """``val_kp_acc/<name>`` and ``val_kp_acc_decoded/<name>`` of each object of a run of
    several (``hits``: N rows of found, visible, found_decoded, visible_decoded); {} for one."""
    if len(names) < 2:
        return {}
    out = {}
    for name, (f, v, fd, vd) in zip(names, hits):
        out[f"val_kp_acc/{name}"] = f / v if v else float("nan")
        out[f"val_kp_acc_decoded/{name}"] = fd / vd if vd else float("nan")
    return out
