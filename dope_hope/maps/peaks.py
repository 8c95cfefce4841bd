"""Belief maps -> sub-pixel keypoint peaks with their heights (:func:`find_peaks`); the first
two steps of the decoders of :mod:`dope_hope.maps.decode` (which group the peaks).

All channels at once, no Python loops over pixels:

1. **Peaks.** Each belief map is smoothed with a Gaussian (``smooth_sigma`` map px,
   ``scipy.ndimage.gaussian_filter``); a cell is a peak when it is the maximum of its
   ``(2*nms_radius+1)^2`` neighbourhood and its belief (the largest raw value in its 3x3
   neighbourhood) exceeds ``threshold`` and, with ``noise_sigmas`` (the decoders' default
   :data:`DEFAULT_NOISE_SIGMAS`), its channel's background by that many robust standard
   deviations (median + ``noise_sigmas`` x 1.4826 MAD of the raw map): on a map with noise
   near the threshold every noise blob would pass, and the grouping and pose search would
   pay for each (a network's background is near zero, where this adds nothing). Plateaus
   of equal maxima yield one peak (connected components, ``scipy.ndimage.label``, only
   where peak cells touch).
2. **Sub-pixel position.** The peak cell first climbs to the raw map's local maximum next to
   it (smoothing moves a skewed peak's cell towards its shoulder; fitting there put a trained
   model's keypoints ~1 cell off). Then a separable *log-parabola* (Gaussian) fit on the three
   samples through the peak cell along x and along y: for ``f = exp(-(x-m)^2 / 2s^2)`` the log is
   an exact parabola, so the vertex is the Gaussian's centre whatever its sigma. The fit
   uses the raw map (exact on ``targets`` output, as DOPE also refines on the unsmoothed
   map), falling back to the smoothed map where the raw samples are not log-concave. At the
   map border the stencil is shifted inwards (one-sided fit), so a keypoint whose Gaussian
   centre lies *outside* the map is recognised as such and dropped: only positions inside
   ``[-0.5, w - 0.5] x [-0.5, h - 0.5]`` map px are kept. The decoders then take the continuous
   map position through :func:`dope_hope.maps.grid.map_to_image`, the inverse of what ``targets``
   used: no other offset anywhere (DOPE's ``OFFSET_DUE_TO_UPSAMPLING = 0.4395`` is not needed).

Scores: ``Peaks.score`` is each peak's height: the fitted Gaussian height on the raw map
(``ln h = h_x + h_y - ln f(cell)``, exact for a separable Gaussian, so a perfect prediction
scores 1 whatever its sub-pixel phase), or the raw 3x3 maximum (at the cell the peak climbed
to) where the fit fails.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter, label

from dope_hope.geometry import inside_image

#: Official DOPE ``config_pose.yaml`` values, for reference: thresh_map 0.01 (peak detection
#: on the smoothed map), thresh_points 0.1 (a peak is used), thresh_angle 0.5, sigma 3.
DEFAULT_THRESHOLD = 0.1
#: DOPE smooths with sigma 3 map px; with 0.5-px targets that merges peaks of neighbouring
#: instances closer than ~3 cells (24 image px at stride 8), so we smooth less by default.
DEFAULT_SMOOTH_SIGMA = 1.0
#: The decoders' default (``DecodeSettings.noise_sigmas``): a peak stands this many robust
#: standard deviations above its map's background. Gaussian noise of std s makes ~150 peaks
#: per channel of an 80x60 map, up to ~4 s high: about one per channel passes 4 s (3.5-5 s find
#: as many boxes on bench/postprocess.py's noise 0.1 / 0.3 maps; 6 s loses weakened true peaks).
DEFAULT_NOISE_SIGMAS = 4.0
#: Cells of each channel sampled for its background level: a strided subsample of between
#: this many and four times as many (the floor of 512 noise samples is within ~6 % of 4 std).
_NOISE_SAMPLE_CELLS = 512


@dataclass
class Peaks:
    """Peaks of all belief channels, concatenated.

    channel: (P,) int, keypoint index 0..8.
    cell: (P, 2) int, (x, y) map cell of the peak.
    xy: (P, 2) float, refined continuous map position (x, y).
    score: (P,) float, peak height (fitted Gaussian height, else the raw 3x3 maximum).
    """

    channel: np.ndarray
    cell: np.ndarray
    xy: np.ndarray
    score: np.ndarray


def split_peaks(peaks: Peaks, groups: int, channels: int) -> list[Peaks]:
    """The peaks of maps stacked as ``groups`` blocks of ``channels`` channels (several objects'
    belief maps searched at once) as one :class:`Peaks` per block, its channels numbered from 0.
    Every step of :func:`find_peaks` works channel by channel, so a block's peaks (values and
    order) are those of a search over that block alone."""
    block = peaks.channel // channels
    out = []
    for g in range(groups):
        keep = block == g
        out.append(Peaks(peaks.channel[keep] - g * channels, peaks.cell[keep], peaks.xy[keep], peaks.score[keep]))
    return out


def as_map_array(a) -> np.ndarray:
    """Accept numpy arrays or torch tensors (any device); drop a leading batch of 1."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 4:
        if a.shape[0] != 1:
            raise ValueError(f"decode one image at a time, got a batch of {a.shape[0]}")
        a = a[0]
    return a


def _log_parabola(maps: np.ndarray, c: np.ndarray, y: np.ndarray, x: np.ndarray, axis: int):
    """Vertex of the parabola through log-samples at (pos-1, pos, pos+1) along ``axis``.

    maps (C, h, w); c, y, x (P,) int indices of the peak cells; axis 1 (y) or 2 (x).
    The stencil is shifted inwards at the border (one-sided, extrapolating fit).
    Returns (vertex (P,) float map coordinate along the axis, valid (P,) bool,
    log_height (P,) float: the parabola's value at its vertex).
    """
    n = maps.shape[axis]
    pos = y if axis == 1 else x
    if n < 3:
        return pos.astype(np.float64), np.zeros(pos.shape, dtype=bool), np.zeros(pos.shape)
    mid = np.clip(pos, 1, n - 2)
    eps = 1e-30

    def sample(offset: int) -> np.ndarray:
        if axis == 1:
            v = maps[c, mid + offset, x]
        else:
            v = maps[c, y, mid + offset]
        return np.log(np.maximum(v.astype(np.float64), eps))

    lo, ce, hi = sample(-1), sample(0), sample(1)
    den = lo - 2.0 * ce + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = mid + 0.5 * (lo - hi) / den
        log_height = ce - (lo - hi) ** 2 / (8.0 * den)
    interior = (pos >= 1) & (pos <= n - 2)
    # Log-concave samples, all three above the floor; an interior peak cell must stay within
    # one cell of the vertex (else the samples are not one Gaussian's).
    valid = (den < 0) & (np.minimum(np.minimum(lo, ce), hi) > np.log(eps) + 1)
    valid &= np.isfinite(vertex) & (~interior | (np.abs(vertex - pos) <= 1.0))
    return np.where(valid, vertex, pos.astype(np.float64)), valid, log_height


def _window_max(a: np.ndarray, radius: int) -> np.ndarray:
    """(C, h, w) maximum of each cell's (2r+1)^2 neighbourhood within its channel, cells
    outside the map not counted (separable: ``cv2.dilate`` along rows with the channels
    stacked, then along columns with them side by side; the replicated border is a cell of
    the map, so it adds nothing)."""
    if radius <= 0:
        return a
    C, h, w = a.shape
    a = np.ascontiguousarray(a, dtype=np.float32)
    size = 2 * radius + 1
    rows = cv2.dilate(a.reshape(C * h, w), np.ones((1, size), np.uint8), borderType=cv2.BORDER_REPLICATE)
    wide = np.ascontiguousarray(rows.reshape(C, h, w).transpose(1, 0, 2)).reshape(h, C * w)
    out = cv2.dilate(wide, np.ones((size, 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return out.reshape(h, C, w).transpose(1, 0, 2)


def _smooth(a: np.ndarray, sigma: float) -> np.ndarray:
    """(C, h, w) float32: ``scipy.ndimage.gaussian_filter(a, (0, sigma, sigma))`` (truncated at
    4 sigma, reflected border, float64 sums, float32 after each axis), computed as two
    ``cv2.sepFilter2D`` passes over all channels at once: columns with the channels side by
    side, rows with them stacked (neither pass mixes channels). scipy where the kernel is
    wider than the map (its reflection repeats, OpenCV's does not)."""
    C, h, w = a.shape
    radius = int(4.0 * float(sigma) + 0.5)
    if radius >= min(h, w):
        return gaussian_filter(a, sigma=(0, sigma, sigma))
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 / (float(sigma) * float(sigma)) * x ** 2)
    kernel = kernel / kernel.sum()
    one = np.ones(1)
    wide = a.transpose(1, 0, 2).reshape(h, C * w).astype(np.float64)
    cols = cv2.sepFilter2D(wide, cv2.CV_64F, one, kernel, borderType=cv2.BORDER_REFLECT).astype(np.float32)
    tall = cols.reshape(h, C, w).transpose(1, 0, 2).reshape(C * h, w).astype(np.float64)
    out = cv2.sepFilter2D(tall, cv2.CV_64F, kernel, one, borderType=cv2.BORDER_REFLECT)
    return out.astype(np.float32).reshape(C, h, w)


_DY = np.repeat([-1, 0, 1], 3)   # the 3x3 neighbourhood, row by row
_DX = np.tile([-1, 0, 1], 3)


def _neighbourhood(raw: np.ndarray, c: np.ndarray, y: np.ndarray, x: np.ndarray):
    """Values (P, 9) of each cell's 3x3 neighbourhood in raw (C, h, w), clamped at the map
    border, row by row, with their (P, 9) rows and columns."""
    h, w = raw.shape[1:]
    yy = np.clip(y[:, None] + _DY, 0, h - 1)
    xx = np.clip(x[:, None] + _DX, 0, w - 1)
    return raw[c[:, None], yy, xx], yy, xx


def _snap_to_raw_max(raw: np.ndarray, c: np.ndarray, y: np.ndarray, x: np.ndarray,
                     max_steps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Climb from each peak cell to the raw map's local maximum (3x3 steps to the first
    strictly larger neighbourhood maximum, row by row; at most ``max_steps``; ties keep the
    current cell).

    raw (C, h, w); c, y, x (P,) int cells. Returns the new (y, x), each (P,) int."""
    rows = np.arange(len(c))
    for _ in range(max_steps):
        vals, yy, xx = _neighbourhood(raw, c, y, x)
        j = np.argmax(vals, axis=1)
        move = vals[rows, j] > raw[c, y, x]
        if not move.any():
            break
        y, x = np.where(move, yy[rows, j], y), np.where(move, xx[rows, j], x)
    return y, x


def noise_floor(raw: np.ndarray, noise_sigmas: float) -> np.ndarray:
    """(C,) per channel of (C, h, w) maps: median + ``noise_sigmas`` x 1.4826 x the median
    absolute deviation (a Gaussian's std, robust to the few cells the peaks cover), from a
    strided subsample of :data:`_NOISE_SAMPLE_CELLS` to 4x as many cells (every cell of a
    small map); medians by partition (the upper one of an even count)."""
    C, h, w = raw.shape
    step = max(1, int(np.sqrt(h * w / _NOISE_SAMPLE_CELLS)))
    sample = raw[:, ::step, ::step].reshape(C, -1)
    mid = sample.shape[1] // 2
    median = np.partition(sample, mid, axis=1)[:, mid]
    mad = np.partition(np.abs(sample - median[:, None]), mid, axis=1)[:, mid]
    return median + float(noise_sigmas) * 1.4826 * mad


def _peak_cells(raw: np.ndarray, smooth: np.ndarray, raw_near: np.ndarray, local_max: np.ndarray,
                floor: float | np.ndarray, refine_on: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(channel, row, column) of every peak cell: a local maximum of the smoothed map whose raw
    3x3 maximum passes ``floor``, one cell per plateau, moved to the raw maximum beside it when
    fitting the raw map; None when there is none."""
    idx = np.flatnonzero(local_max & (raw_near > floor))
    if idx.size == 0:
        return None
    C, h, w = raw.shape
    c, y, x = np.unravel_index(idx, raw.shape)
    padded = np.zeros((C, h + 2, w + 2), dtype=bool)  # peak cells, one empty cell around
    padded[c, y + 1, x + 1] = True
    if any(padded[c, y + 1 + dy, x + 1 + dx].any() for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1))):
        # Touching peak cells (a plateau): label connected peak cells within each channel,
        # keep the first cell of each.
        structure = np.zeros((3, 3, 3), dtype=bool)
        structure[1] = True
        labels, _ = label(padded[:, 1:-1, 1:-1], structure=structure)
        _, first = np.unique(labels.ravel()[idx], return_index=True)
        c, y, x = np.unravel_index(idx[first], labels.shape)

    if refine_on == "raw" and smooth is not raw:
        # Smoothing finds the peaks (and keeps close instances apart) but shifts a skewed
        # peak's cell; fit the raw map around its own maximum next to the detected cell.
        climb = np.flatnonzero(raw_near[c, y, x] > raw[c, y, x])   # not the raw maximum of their 3x3
        if climb.size:
            y, x = y.copy(), x.copy()
            y[climb], x[climb] = _snap_to_raw_max(raw, c[climb], y[climb], x[climb])
            _, keep = np.unique(np.ravel_multi_index((c, y, x), raw.shape), return_index=True)  # climbed together
            keep.sort()
            c, y, x = c[keep], y[keep], x[keep]
    return c, y, x


def find_peaks(
    belief,
    threshold: float = DEFAULT_THRESHOLD,
    smooth_sigma: float = DEFAULT_SMOOTH_SIGMA,
    nms_radius: int = 1,
    refine_on: str = "raw",
    noise_sigmas: float = DEFAULT_NOISE_SIGMAS,
) -> Peaks:
    """Sub-pixel peaks of every belief channel (see the module docstring). The defaults are
    the decoder's (:class:`dope_hope.maps.decode.DecodeSettings`, which owns them and is built
    from the same constants): the decoders, inference and validation find their peaks through
    :func:`dope_hope.maps.decode.decoder_peaks` with their settings.

    Args:
        belief: (C, h, w) belief maps (numpy or torch; a leading batch of 1 is dropped).
        threshold: minimum belief at a peak.
        smooth_sigma: Gaussian smoothing for detection, map px (0 = none).
        nms_radius: a peak is the maximum of its (2r+1)^2 neighbourhood, map px.
        refine_on: "raw" (default) or "smoothed": which map the log-parabola fit uses first.
        noise_sigmas: a peak also exceeds its channel's :func:`noise_floor` by this many robust
            standard deviations (0: no floor, ``threshold`` alone).

    Returns:
        :class:`Peaks` with positions in continuous map coordinates inside the map.
    """
    if refine_on not in ("raw", "smoothed"):
        raise ValueError(f"refine_on must be 'raw' or 'smoothed', got {refine_on!r}")
    if not noise_sigmas >= 0.0:
        raise ValueError(f"noise_sigmas must be >= 0, got {noise_sigmas}")
    raw = as_map_array(belief)
    if raw.ndim != 3:
        raise ValueError(f"belief must be (C, h, w), got {raw.shape}")
    if not np.isfinite(raw).all():
        raw = np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
    smooth = _smooth(raw, smooth_sigma) if smooth_sigma > 0 else raw
    local_max = (smooth >= _window_max(smooth, nms_radius)) & (smooth > 0)  # flat empty regions are not peaks
    # A peak: a local maximum of the smoothed map whose raw 3x3 maximum (cells inside the map) passes.
    raw_near = _window_max(raw, 1)
    floor = threshold
    if noise_sigmas > 0:
        floor = np.maximum(threshold, noise_floor(raw, noise_sigmas))[:, None, None]
    cells = _peak_cells(raw, smooth, raw_near, local_max, floor, refine_on)
    if cells is None:
        empty = np.zeros((0, 2))
        return Peaks(np.zeros(0, int), empty.astype(int), empty, np.zeros(0))
    c, y, x = cells
    xy, score, inside = _subpixel_fit(raw, smooth, raw_near, c, y, x, refine_on)
    return Peaks(
        channel=c[inside].astype(int),
        cell=np.stack([x, y], axis=1)[inside].astype(int),
        xy=xy[inside],
        score=score[inside],
    )


def _subpixel_fit(raw: np.ndarray, smooth: np.ndarray, raw_near: np.ndarray, c: np.ndarray, y: np.ndarray,
                  x: np.ndarray, refine_on: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 of the module docstring and the scores, for the peak cells (c, y, x) ((P,) int
    each) of the raw and smoothed (C, h, w) maps (``raw_near``: the raw 3x3 maxima): ((P, 2)
    continuous map position (x, y), (P,) score, (P,) bool: the position lies inside the map)."""
    h, w = raw.shape[1:]
    primary, secondary = (raw, smooth) if refine_on == "raw" else (smooth, raw)
    coords, heights, raw_ok = [], [], []
    inside = np.ones(len(c), dtype=bool)
    for axis in (2, 1):  # x then y
        v1, ok1, h1 = _log_parabola(primary, c, y, x, axis)
        v2, ok2 = v1.copy(), np.zeros(len(c), dtype=bool)  # the other map, where the first fit fails
        redo = np.flatnonzero(~ok1)
        if redo.size:
            v2[redo], ok2[redo], _ = _log_parabola(secondary, c[redo], y[redo], x[redo], axis)
        if primary is raw:
            hr, okr = h1, ok1
        else:
            _, okr, hr = _log_parabola(raw, c, y, x, axis)
        heights.append(hr)
        raw_ok.append(okr)
        pos = y if axis == 1 else x
        n_axis = h if axis == 1 else w
        coords.append(np.where(ok1, v1, np.where(ok2, v2, pos.astype(np.float64))))
        # A border cell is only a keypoint if a fit places the Gaussian inside the map: a
        # monotonic ramp towards the border means the keypoint lies beyond it.
        border = (pos == 0) | (pos == n_axis - 1)
        inside &= ~(border & ~ok1 & ~ok2) | (n_axis < 3)
    xy = np.stack(coords, axis=1)
    # Score: the fitted Gaussian height on the raw map (independent of the sub-pixel phase;
    # for a separable Gaussian ln peak = h_x + h_y - ln f(cell)), else the raw 3x3 maximum.
    value = raw_near[c, y, x].astype(np.float64)  # at the cell fitted (after the climb)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        fitted = np.exp(heights[0] + heights[1] - np.log(np.maximum(raw[c, y, x], 1e-30)))
    score = np.where(raw_ok[0] & raw_ok[1] & np.isfinite(fitted), np.maximum(fitted, value), value)
    inside &= inside_image(xy, (h, w))
    return xy, score, inside
