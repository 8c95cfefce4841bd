"""Belief maps + affinity fields -> object instances with 2D keypoints and scores.

Pipeline (all channels at once, no Python loops over pixels):

1-2. **Peaks** and their **sub-pixel positions** and heights: :func:`dope_hope.maps.peaks.find_peaks`
   (smoothing, non-maximum suppression, the noise floor, the log-parabola fit; the module
   docstring there).
3. **Grouping.** Every centroid peak (channel 8) starts an instance. For corner type k, each
   corner peak reads the affinity vector ``v`` at its cell; for each centroid ``c`` the
   direction ``u`` from that cell centre to ``c`` is compared with ``v``: the pair is feasible
   when ``|v/|v| - u| < angle_threshold`` (DOPE's test, 0.5 = about 29 deg) and ``|v| >=
   min_affinity``. Among feasible pairs stronger peaks go first and each takes the nearest
   centroid (DOPE's rule), solved as a one-to-one assignment per corner type
   (``scipy.optimize.linear_sum_assignment`` on corner-centroid distance plus a peak-height
   priority), so an instance never receives two corners of one type, two touching instances
   do not steal each other's corners, and a weak secondary peak next to the centroid does not
   displace the strong true corner. The field gives only a direction (no length), so the
   centroid distance is the only distance cue.
4. **Candidates** (:func:`corner_candidates`, what
   :class:`dope_hope.inference.predictor.DopePredictor` uses by default): instead of
   committing to one peak per corner type, each centroid keeps up to ``max_per_type``
   feasible peaks of every type (the one-to-one grouping's choice first, then strongest,
   nearest among equals), shared with other centroids, but not the peaks of other objects
   that merely pass the angle test: a peak whose affinity points at another centroid clearly
   better (``angle_margin``), or that lies farther than ``size_factor`` times the object's
   projected size (the median distance of its one-to-one corners), is no candidate.
   :func:`dope_hope.inference.pose_search.solve_pnp_candidates` then picks the combination that a
   rigid cuboid explains. A trained net often puts a second peak of map k on another corner
   of the same box (corner identity is the hard part); the grouping above must guess, the
   pose search need not.

Scores: ``Instance2D.scores[k]`` is the height of keypoint k's peak (:class:`~dope_hope.maps.peaks.Peaks`),
0 where missing. ``Instance2D.score`` = ``scores.sum() / 9`` (mean over all nine, missing
keypoints count 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from dope_hope.config import (
    SectionSettings,
    at_least,
    finite_float,
    nonnegative_float,
    one_of,
    or_inf,
    positive_float,
)
from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS
from dope_hope.maps.grid import map_to_image
from dope_hope.maps.peaks import (
    DEFAULT_NOISE_SIGMAS,
    DEFAULT_SMOOTH_SIGMA,
    DEFAULT_THRESHOLD,
    Peaks,
    as_map_array,
    find_peaks,
)

#: DOPE's thresh_angle.
DEFAULT_ANGLE_THRESHOLD = 0.5
#: :func:`corner_candidates`: a peak joins a centroid other than its one-to-one one only when
#: its affinity points at it at most this much worse than at its best-aimed centroid, and it
#: lies within this many times the centroid's object size.
DEFAULT_ANGLE_MARGIN = 0.2
DEFAULT_SIZE_FACTOR = 2.0
#: Grouping cost per unit of missing peak height, map px: a peak's height outranks any
#: centroid distance (see :func:`assign_corners`).
SCORE_PRIORITY = 1e4


@dataclass(frozen=True)
class DecodeSettings(SectionSettings):
    """The decoders' settings (``decode:`` in ``dope_hope/configs/infer.yaml``), shared by
    :func:`decode_maps` and :func:`corner_candidates`; the official DOPE values in brackets.

    Peaks (:func:`~dope_hope.maps.peaks.find_peaks`, :data:`PEAK_OPTIONS`): threshold: minimum belief at a keypoint
    peak (thresh_points 0.1). smooth_sigma: detection smoothing, map px (3; 0 = none).
    nms_radius: local-maximum neighbourhood radius, map px. refine_on: "raw" or "smoothed",
    the map the sub-pixel fit uses first. noise_sigmas: a peak stands this many robust
    standard deviations above its map's background (:func:`~dope_hope.maps.peaks.noise_floor`; 0: only
    ``threshold``).

    Grouping: angle_threshold: corner-centroid direction test, unit-vector distance (0.5).
    min_affinity: minimum affinity vector length at a corner peak. min_keypoints
    (:func:`decode_maps`): drop instances with fewer keypoints (the centroid counts).

    Candidates (:func:`corner_candidates`): max_per_type: keep at most this many peaks of each
    corner type per centroid: the one :func:`decode_maps` would give it, then the others by its
    grouping cost (strongest first, nearest among equals). angle_margin: a peak other than the
    one-to-one choice is a candidate of a centroid only when its affinity points at it at most
    this much worse (unit-vector distance) than at the centroid it points at best (inf: no
    bound). size_factor: no peak, the one-to-one choice included, lies farther from a centroid
    than this many times its object's size: the median distance of its one-to-one corners
    (inf: no bound).
    """

    SECTION = "decode"
    RULES = {"threshold": finite_float, "angle_threshold": nonnegative_float, "smooth_sigma": nonnegative_float,
             "nms_radius": at_least(0), "min_affinity": finite_float, "refine_on": one_of("raw", "smoothed"),
             "min_keypoints": at_least(0), "noise_sigmas": nonnegative_float, "max_per_type": at_least(1),
             "angle_margin": or_inf(nonnegative_float), "size_factor": or_inf(positive_float)}

    threshold: float = DEFAULT_THRESHOLD
    angle_threshold: float = DEFAULT_ANGLE_THRESHOLD
    smooth_sigma: float = DEFAULT_SMOOTH_SIGMA
    nms_radius: int = 1
    min_affinity: float = 0.0
    refine_on: str = "raw"
    min_keypoints: int = 1
    noise_sigmas: float = DEFAULT_NOISE_SIGMAS
    max_per_type: int = 3
    angle_margin: float = DEFAULT_ANGLE_MARGIN
    size_factor: float = DEFAULT_SIZE_FACTOR


@dataclass
class Instance2D:
    """One detected object in image pixels.

    keypoints: (9, 2) float, image px (u, v); NaN where a keypoint was not found.
    scores: (9,) float, peak height of each keypoint (see the module docstring); 0 if missing.
    score: float, ``scores.sum() / 9``.
    """

    keypoints: np.ndarray
    scores: np.ndarray
    score: float

    @property
    def present(self) -> np.ndarray:
        """(9,) bool, keypoints that were found."""
        return np.all(np.isfinite(self.keypoints), axis=1)


def assign_corners(
    corner_cells: np.ndarray,
    corner_xy: np.ndarray,
    vectors: np.ndarray,
    centroids_xy: np.ndarray,
    angle_threshold: float = DEFAULT_ANGLE_THRESHOLD,
    min_affinity: float = 0.0,
    corner_scores: np.ndarray | None = None,
) -> np.ndarray:
    """One-to-one assignment of the peaks of one corner type to centroids.

    Among feasible pairs, stronger peaks go first and each takes its nearest centroid: the
    cost is ``distance + SCORE_PRIORITY * (1 - score)``. With more peaks of a type than
    centroids (a trained net leaves weak secondary peaks near strong ones), the weak ones
    stay unassigned even when they lie nearer to the centroid; with equal scores it is
    DOPE's nearest-centroid rule.

    Args:
        corner_cells: (n, 2) int map cells (x, y) of the corner peaks.
        corner_xy: (n, 2) refined corner positions, map px.
        vectors: (n, 2) affinity vectors read at the corner cells.
        centroids_xy: (m, 2) centroid positions, map px.
        angle_threshold: maximum |v/|v| - u| (unit-vector distance; 0.5 ~ 29 deg).
        min_affinity: minimum |v| for the field to count.
        corner_scores: (n,) peak heights (None: all equal).

    Returns:
        (n,) int: the centroid index of each corner peak, -1 where none is feasible.
    """
    n, m = len(corner_xy), len(centroids_xy)
    if n == 0 or m == 0:
        return np.full(n, -1, dtype=int)
    feasible, cost, _, _ = corner_centroid_costs(corner_cells, corner_xy, vectors, centroids_xy, angle_threshold,
                                                 min_affinity, corner_scores)
    return _one_to_one(feasible, cost)


def _one_to_one(feasible: np.ndarray, cost: np.ndarray, kinds: np.ndarray | None = None) -> np.ndarray:
    """(n,) int centroid of each corner peak under the one-to-one assignment of the (n, m)
    ``feasible`` pairs at least total ``cost``; -1 where none (see :func:`assign_corners`).
    With ``kinds`` ((n,) int corner type of each peak) one assignment per type, solved as one
    block-diagonal problem (a column per type and centroid; another type's column is
    infeasible), which has the per-type assignments as its optimum."""
    n, m = cost.shape
    out = np.full(n, -1, dtype=int)
    if cost.size == 0:
        return out
    big = 1e9 + cost.max()
    if kinds is None:
        kinds = np.zeros(n, dtype=int)
    types, block = np.unique(kinds, return_inverse=True)
    full = np.full((n, len(types) * m), big)
    full[np.arange(n)[:, None], block[:, None] * m + np.arange(m)] = np.where(feasible, cost, big)
    rows, cols = linear_sum_assignment(full)
    keep = (cols // m == block[rows]) & feasible[rows, cols % m]
    out[rows[keep]] = cols[keep] % m
    return out


def corner_centroid_costs(corner_cells: np.ndarray, corner_xy: np.ndarray, vectors: np.ndarray,
                          centroids_xy: np.ndarray, angle_threshold: float = DEFAULT_ANGLE_THRESHOLD,
                          min_affinity: float = 0.0, corner_scores: np.ndarray | None = None,
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(n, m) bool feasibility (affinity direction test), (n, m) float grouping cost, (n, m)
    float direction disagreement ``|v/|v| - u|`` and (n, m) corner-centroid distance (map px)
    of corner peaks vs centroids; arguments as in :func:`assign_corners`."""
    vnorm = np.linalg.norm(vectors, axis=1)
    v_hat = vectors / np.where(vnorm > 0, vnorm, 1.0)[:, None]
    to_c = centroids_xy[None, :, :] - corner_cells[:, None, :].astype(np.float64)  # (n, m, 2)
    dist_c = np.linalg.norm(to_c, axis=2)
    u_hat = to_c / np.where(dist_c > 0, dist_c, 1.0)[..., None]
    angle_dist = np.linalg.norm(u_hat - v_hat[:, None, :], axis=2)
    feasible = (angle_dist < angle_threshold) & (vnorm[:, None] > max(min_affinity, 0.0))
    feasible &= dist_c > 0
    dist = np.linalg.norm(centroids_xy[None] - corner_xy[:, None], axis=2)
    cost = dist
    if corner_scores is not None:
        weak = 1.0 - np.clip(np.asarray(corner_scores, dtype=np.float64), 0.0, 1.0)
        cost = dist + SCORE_PRIORITY * weak[:, None]
    return feasible, cost, angle_dist, dist


#: The decode options that choose the peaks (the rest shape the grouping).
PEAK_OPTIONS = ("threshold", "smooth_sigma", "nms_radius", "refine_on", "noise_sigmas")


def decoder_peaks(belief, settings: DecodeSettings = DecodeSettings()) -> Peaks:
    """The peaks :func:`decode_maps` and :func:`corner_candidates` start from under
    ``settings`` (its peak ones, :data:`PEAK_OPTIONS`): computed once, they can be handed to
    either decoder (``peaks=``) and, as channels and heights, to :func:`keypoint_score_bound`."""
    return find_peaks(belief, settings.threshold, settings.smooth_sigma, settings.nms_radius, settings.refine_on,
                      settings.noise_sigmas)


#: A pose's score and its bound are sums of the same clipped peak heights in other orders: a
#: skip below a threshold leaves this much for rounding, so it never drops a pose the
#: threshold keeps (:func:`may_reach`).
SCORE_BOUND_SLACK = 1e-9


def may_reach(bound: float, min_score: float) -> bool:
    """Whether a pose whose score is at most ``bound`` (:func:`keypoint_score_bound`) may reach
    ``min_score`` (always where min_score <= 0)."""
    return min_score <= 0 or bound >= min_score - SCORE_BOUND_SLACK


def keypoint_score_bound(keypoint_ids: np.ndarray, heights: np.ndarray, min_points: int | None = None) -> float:
    """The highest pose score keypoint peaks of these types ((n,) int 0..8) and heights ((n,))
    allow: the mean over the nine keypoint types of each type's highest peak, clipped to
    [0, 1]. A pose scores the mean of its inlier keypoints' peak heights, one peak per type,
    clipped (:mod:`dope_hope.inference.pnp`), so no pose decoded from these peaks scores more;
    below a score threshold the decoding can be skipped.
    ``min_points``: the bound of a score divided by at least that many keypoints (the in-view
    score, :func:`dope_hope.inference.pnp.score_in_view`, divides by at least the inliers a pose
    needs: :func:`dope_hope.inference.pnp.least_score_divisor`): the mean of the ``min_points``
    highest of those per-type peaks. (A plain loop: the decoder calls it per centroid, on a
    few to a few hundred peaks, where numpy's per-call cost is most of the time.)"""
    best = [0.0] * NUM_KEYPOINTS
    for kind, height in zip(np.asarray(keypoint_ids, dtype=int).ravel().tolist(),
                            np.asarray(heights, dtype=np.float64).ravel().tolist()):
        if height > best[kind]:  # NaN and negative heights never count
            best[kind] = min(height, 1.0)
    if min_points is None:
        return sum(best) / NUM_KEYPOINTS
    k = min(int(min_points), NUM_KEYPOINTS)
    return sum(sorted(best, reverse=True)[:k]) / k


def decode_maps(
    belief,
    affinity,
    stride: int,
    settings: DecodeSettings = DecodeSettings(),
    peaks: Peaks | None = None,
) -> list[Instance2D]:
    """Decode one image's maps into instances (DOPE's grouping: one corner per type).

    Args:
        belief: (9, h, w) belief maps, numpy or torch (a leading batch of 1 is dropped).
        affinity: (16, h, w) affinity fields, same kind.
        stride: image pixels per map cell (8 for the 50-px head, 1 for the 400-px head).
        settings: :class:`DecodeSettings` (peaks, grouping, ``min_keypoints``).
        peaks: the :func:`decoder_peaks` of these maps and settings, when already found.
    Returns:
        Instances sorted by decreasing score; keypoints in image px via mapgrid.
    """
    peaks, aff = _peaks_and_field(belief, affinity, settings, peaks)
    is_c = peaks.channel == CENTROID_INDEX
    centroids_xy = peaks.xy[is_c]
    m = len(centroids_xy)
    if m == 0:
        return []
    kp_map = np.full((m, NUM_KEYPOINTS, 2), np.nan)
    scores = np.zeros((m, NUM_KEYPOINTS))
    kp_map[:, CENTROID_INDEX] = centroids_xy
    scores[:, CENTROID_INDEX] = peaks.score[is_c]
    corner, *_, owner = _corner_groups(peaks, aff, centroids_xy, settings)
    got = owner >= 0
    kp_map[owner[got], peaks.channel[corner[got]]] = peaks.xy[corner[got]]
    scores[owner[got], peaks.channel[corner[got]]] = peaks.score[corner[got]]

    kp_img = map_to_image(kp_map, stride)
    instances = [
        Instance2D(keypoints=kp_img[i], scores=scores[i], score=float(scores[i].sum() / NUM_KEYPOINTS))
        for i in range(m)
        if np.isfinite(kp_img[i, :, 0]).sum() >= settings.min_keypoints
    ]
    instances.sort(key=lambda inst: -inst.score)
    return instances


def _peaks_and_field(belief, affinity, settings: DecodeSettings,
                     peaks: Peaks | None = None) -> tuple[Peaks, np.ndarray]:
    """Checked maps -> (peaks of all nine channels (``peaks`` when given: :func:`decoder_peaks`
    of the same maps and settings), (16, h, w) affinity)."""
    bel = as_map_array(belief)
    aff = as_map_array(affinity)
    if bel.ndim != 3 or bel.shape[0] != NUM_KEYPOINTS:
        raise ValueError(f"belief must be ({NUM_KEYPOINTS}, h, w), got {bel.shape}")
    if aff.shape != (2 * CENTROID_INDEX,) + bel.shape[1:]:
        raise ValueError(f"affinity must be ({2 * CENTROID_INDEX}, h, w) like belief, got {aff.shape}")
    if peaks is not None:
        return peaks, aff
    return decoder_peaks(bel, settings), aff


def _corner_groups(peaks: Peaks, aff: np.ndarray, centroids_xy: np.ndarray,
                   settings: DecodeSettings) -> tuple[np.ndarray, ...]:
    """The grouping step both :func:`decode_maps` and :func:`corner_candidates` build on, for
    every corner peak against the (m, 2) centroids at once: ((N,) peak indices of the corner
    peaks, (N, m) feasible, (N, m) cost, (N, m) direction disagreement, (N, m) distance, (N,)
    one-to-one centroid or -1, assigned per corner type). The affinity is read at each peak's cell
    (NaN/inf read as 0)."""
    corner = np.flatnonzero(peaks.channel != CENTROID_INDEX)
    ch, cells = peaks.channel[corner], peaks.cell[corner]
    vectors = np.stack([aff[2 * ch, cells[:, 1], cells[:, 0]], aff[2 * ch + 1, cells[:, 1], cells[:, 0]]], 1)
    vectors = vectors.astype(np.float64)
    vectors[~np.isfinite(vectors)] = 0.0
    feasible, cost, angle, dist = corner_centroid_costs(cells, peaks.xy[corner], vectors, centroids_xy,
                                                        settings.angle_threshold, settings.min_affinity,
                                                        peaks.score[corner])
    return corner, feasible, cost, angle, dist, _one_to_one(feasible, cost, ch)


@dataclass
class CornerCandidates:
    """One centroid and the corner peaks that may belong to it (image px).

    keypoint_ids: (n,) int, keypoint index of each entry; entry 0 is the centroid (id 8).
    xy: (n, 2) float, image px (u, v).
    scores: (n,) float, peak heights.
    """

    keypoint_ids: np.ndarray
    xy: np.ndarray
    scores: np.ndarray

    @property
    def score(self) -> float:
        """Height of the centroid peak."""
        return float(self.scores[0])


def corner_candidates(
    belief,
    affinity,
    stride: int,
    settings: DecodeSettings = DecodeSettings(),
    peaks: Peaks | None = None,
) -> list[CornerCandidates]:
    """Per centroid peak, the corner peaks whose affinity points at it (module docstring, 4).

    Args:
        belief, affinity, stride, peaks: as in :func:`decode_maps`.
        settings: :class:`DecodeSettings` (peaks, grouping, and which peaks are candidates:
            ``max_per_type``, ``angle_margin``, ``size_factor``).

    Returns:
        One :class:`CornerCandidates` per centroid peak, strongest centroid first. A corner
        peak may be a candidate of several centroids.
    """
    peaks, aff = _peaks_and_field(belief, affinity, settings, peaks)
    is_c = peaks.channel == CENTROID_INDEX
    centroids_xy = peaks.xy[is_c]
    m = len(centroids_xy)
    if m == 0:
        return []
    corner, feasible, cost, angle, dist, owner = _corner_groups(peaks, aff, centroids_xy, settings)
    ch = peaks.channel[corner]
    size = _object_sizes(owner, ch, dist, m)
    # Who may be a candidate of whom, ranked: the one-to-one choice, then by the grouping cost.
    rows = np.arange(m)
    best_angle = np.min(np.where(feasible, angle, np.inf), axis=1, keepdims=True)      # (N, 1)
    near = dist <= settings.size_factor * size[None]
    keep = feasible & (angle <= best_angle + settings.angle_margin) & near
    is_owner = (owner[:, None] == rows[None]) & near
    rank = np.where(is_owner, -np.inf, np.where(keep, cost, np.inf))
    table = _candidate_table(rank, ch, corner, np.flatnonzero(is_c), settings.max_per_type)
    bounds = np.searchsorted(table[:, 0], np.arange(m + 1))
    ids = np.where(table[:, 1] < 0, CENTROID_INDEX, table[:, 1])
    xy = map_to_image(peaks.xy[table[:, 3]], stride)
    sc = peaks.score[table[:, 3]].astype(np.float64)
    out = [CornerCandidates(keypoint_ids=ids[a:b], xy=xy[a:b], scores=sc[a:b])
           for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist())]
    out.sort(key=lambda cand: -cand.score)
    return out


def _object_sizes(owner: np.ndarray, ch: np.ndarray, dist: np.ndarray, m: int) -> np.ndarray:
    """(m,) size of each centroid's object, map px: the median distance of its one-to-one
    corners (inf where it has none). owner: (N,) one-to-one centroid of each corner peak or
    -1; ch: (N,) their corner types; dist: (N, m) corner-centroid distances."""
    own = np.flatnonzero(owner >= 0)
    own_dist = np.full((m, CENTROID_INDEX), np.inf)
    own_dist[owner[own], ch[own]] = dist[own, owner[own]]
    own_dist.sort(axis=1)
    n_own = np.isfinite(own_dist).sum(axis=1)
    rows = np.arange(m)
    lo, hi = own_dist[rows, np.maximum(n_own - 1, 0) // 2], own_dist[rows, np.maximum(n_own, 1) // 2]
    return np.where(n_own > 0, 0.5 * (lo + hi), np.inf)


def _candidate_table(rank: np.ndarray, ch: np.ndarray, corner: np.ndarray, centroids: np.ndarray,
                     max_per_type: int) -> np.ndarray:
    """(k, 4) int rows (centroid, type, rank, peak index), sorted: each centroid itself (type
    -1: first), then its entries. rank: (N, m) of each corner peak for each centroid (-inf: its
    one-to-one choice, inf: no candidate); ch, corner: (N,) the corner peaks' types and peak
    indices; centroids: (m,) the centroid peaks' indices. Per centroid (column) the corner peaks
    by type, then rank (stable): the first ``max_per_type`` of each type, where ranked, are its
    entries."""
    m = rank.shape[1]
    by = np.lexsort((rank, np.broadcast_to(ch[:, None], rank.shape)), axis=0)          # (N, m)
    kinds = np.sort(ch)
    place = np.arange(len(ch)) - np.searchsorted(kinds, kinds)                          # rank within its type
    r, c = np.nonzero((place[:, None] < max_per_type) & (np.take_along_axis(rank, by, axis=0) < np.inf))
    table = np.concatenate([np.stack([np.arange(m), np.full(m, -1), np.zeros(m, dtype=int), centroids], axis=1),
                            np.stack([c, kinds[r], place[r], corner[by[r, c]]], axis=1)])
    return table[np.lexsort((table[:, 2], table[:, 1], table[:, 0]))]
