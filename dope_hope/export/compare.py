"""Map and keypoint deviation between two models' outputs on the same images."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import linear_sum_assignment

from dope_hope.maps.decode import DecodeSettings, decode_maps
from dope_hope.maps.peaks import find_peaks

if TYPE_CHECKING:
    from dope_hope.maps.decode import DecodeSettings


# ----------------------------------------------------------------------------- results
@dataclass
class MapDeviation:
    """How far a model's maps and decoded keypoints are from a reference's.

    images: number of images compared. max_abs / mean_abs: over all belief + affinity
    values; belief_max_abs: belief maps only. instances_ref / instances_test: decoded
    instances; instances_matched: pairs matched by centroid. keypoints_compared: keypoints
    found in both of a matched pair; keypoints_lost / keypoints_added: found in only the
    reference / only the test instance. median_px / max_px: keypoint distance, image px
    (NaN when nothing was compared); p95_px: its 95th percentile. peaks_*: the same per
    belief peak, without grouping (every sub-pixel peak of the reference above the decode
    threshold, matched one-to-one to the test's peaks of the same channel within one map
    cell): meaningful even for maps that decode no instance (e.g. untrained weights).
    """

    images: int
    max_abs: float
    mean_abs: float
    belief_max_abs: float
    instances_ref: int
    instances_test: int
    instances_matched: int
    keypoints_compared: int
    keypoints_lost: int
    keypoints_added: int
    median_px: float
    max_px: float
    p95_px: float = float("nan")
    peaks_ref: int = 0
    peaks_matched: int = 0
    peak_median_px: float = float("nan")
    peak_max_px: float = float("nan")

    def summary(self) -> str:
        """One line for reports."""
        kp = (f"keypoints: median {self.median_px:.3f} px, p95 {self.p95_px:.3f} px, max "
              f"{self.max_px:.3f} px over {self.keypoints_compared} ({self.keypoints_lost} lost, "
              f"{self.keypoints_added} added; instances {self.instances_matched}/{self.instances_ref} matched)"
              if self.keypoints_compared else
              f"keypoints: none to compare (reference decodes {self.instances_ref} instances)")
        peaks = (f"; peaks: median {self.peak_median_px:.3f} px, max {self.peak_max_px:.3f} px, "
                 f"{self.peaks_matched}/{self.peaks_ref} matched" if self.peaks_ref else "")
        return (f"maps max |d| {self.max_abs:.4g}, mean |d| {self.mean_abs:.3g} "
                f"(belief max {self.belief_max_abs:.4g}) over {self.images} images; {kp}{peaks}")


# ----------------------------------------------------------------------------- comparison
def _match_instances(ref, test, max_px: float):
    if not ref or not test:
        return []
    a = np.array([r.keypoints[8] for r in ref])
    b = np.array([t.keypoints[8] for t in test])
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    d = np.where(np.isfinite(d), d, 1e9)
    rows, cols = linear_sum_assignment(d)
    return [(r, c) for r, c in zip(rows, cols) if d[r, c] <= max_px]


def _peak_distances(ref_belief: np.ndarray, test_belief: np.ndarray, stride: int,
                    threshold: float, smooth_sigma: float) -> tuple[int, np.ndarray]:
    """(number of reference peaks, distances of the matched ones in image px)."""
    # every peak above the threshold (no noise floor): how far precision moves each peak
    pr = find_peaks(ref_belief, threshold=threshold, smooth_sigma=smooth_sigma, noise_sigmas=0.0)
    pt = find_peaks(test_belief, threshold=threshold, smooth_sigma=smooth_sigma, noise_sigmas=0.0)
    out = []
    for c in np.unique(pr.channel):
        a, b = pr.xy[pr.channel == c], pt.xy[pt.channel == c]
        if not len(b):
            continue
        d = np.linalg.norm(a[:, None] - b[None], axis=2)
        rows, cols = linear_sum_assignment(d)
        keep = d[rows, cols] <= 1.0  # map cells
        out.append(d[rows, cols][keep] * stride)
    return len(pr.channel), (np.concatenate(out) if out else np.zeros(0))


def _object_groups(maps: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """One (belief (9, h, w), affinity (16, h, w)) pair per image and object group."""
    out = []
    for belief, affinity in maps:
        b, a = np.asarray(belief), np.asarray(affinity)
        b, a = b.reshape(b.shape[-3:]), a.reshape(a.shape[-3:])
        for k in range(b.shape[0] // 9):
            out.append((b[9 * k:9 * k + 9], a[16 * k:16 * k + 16]))
    return out


def compare_maps(reference: Sequence[tuple[np.ndarray, np.ndarray]],
                 test: Sequence[tuple[np.ndarray, np.ndarray]], stride: int,
                 match_px: float | None = None, decode: DecodeSettings | None = None) -> MapDeviation:
    """Map and keypoint deviation of ``test`` from ``reference`` (one (belief, affinity) per image).

    Maps: (9K, h, w) and (16K, h, w) per image for K objects (a leading batch of 1 is dropped;
    each object's channel group is compared as if it were an image of its own). Keypoints:
    both are decoded with :func:`dope_hope.maps.decode.decode_maps` (``decode``: its settings,
    default :class:`~dope_hope.maps.decode.DecodeSettings`),
    instances are matched one-to-one by centroid (within ``match_px`` image px, default 4
    map cells), and the distance of every keypoint found in both is measured, image px.
    Belief peaks are also compared one by one, without grouping (:class:`MapDeviation`).
    """
    decode = DecodeSettings() if decode is None else decode

    if len(reference) != len(test) or not reference:
        raise ValueError("compare_maps needs the same non-zero number of reference and test images")
    images = len(reference)
    reference, test = _object_groups(reference), _object_groups(test)
    match_px = 4.0 * stride if match_px is None else float(match_px)
    max_abs = belief_max = 0.0
    abs_sum, count = 0.0, 0
    n_ref = n_test = n_match = lost = added = 0
    dists: list[np.ndarray] = []
    n_peaks, peak_d = 0, []
    for (rb, ra), (tb, ta) in zip(reference, test):
        rb, ra, tb, ta = (np.asarray(x, np.float32).reshape(x.shape[-3:]) for x in (rb, ra, tb, ta))
        db, da = np.abs(rb - tb), np.abs(ra - ta)
        belief_max = max(belief_max, float(db.max()))
        max_abs = max(max_abs, belief_max, float(da.max()))
        abs_sum += float(db.sum(dtype=np.float64) + da.sum(dtype=np.float64))
        count += db.size + da.size
        ri = decode_maps(rb, ra, stride, decode)
        ti = decode_maps(tb, ta, stride, decode)
        n_ref, n_test = n_ref + len(ri), n_test + len(ti)
        for r, c in _match_instances(ri, ti, match_px):
            n_match += 1
            pr, pt = ri[r].present, ti[c].present
            both = pr & pt
            lost += int((pr & ~pt).sum())
            added += int((pt & ~pr).sum())
            dists.append(np.linalg.norm(ri[r].keypoints[both] - ti[c].keypoints[both], axis=1))
        n, pd = _peak_distances(rb, tb, stride, decode.threshold, decode.smooth_sigma)
        n_peaks += n
        peak_d.append(pd)
    d = np.concatenate(dists) if dists else np.zeros(0)
    p = np.concatenate(peak_d)
    return MapDeviation(
        images=images, max_abs=max_abs, mean_abs=abs_sum / max(count, 1), belief_max_abs=belief_max,
        instances_ref=n_ref, instances_test=n_test, instances_matched=n_match,
        keypoints_compared=int(d.size), keypoints_lost=lost, keypoints_added=added,
        median_px=float(np.median(d)) if d.size else float("nan"),
        max_px=float(d.max()) if d.size else float("nan"),
        p95_px=float(np.percentile(d, 95)) if d.size else float("nan"),
        peaks_ref=n_peaks, peaks_matched=int(p.size),
        peak_median_px=float(np.median(p)) if p.size else float("nan"),
        peak_max_px=float(p.max()) if p.size else float("nan"))
