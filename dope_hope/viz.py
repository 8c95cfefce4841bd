"""Overlays on RGB images: projected cuboids, pose axes, keypoints, and image montages.

Every function takes an (H, W, 3) uint8 RGB image and returns a new image (the input is
never modified). Coordinates are pixels with pixel centres at integer coordinates; points
that are NaN (absent keypoints) are skipped. Drawing is anti-aliased and sub-pixel accurate
(OpenCV's fixed-point ``shift``).
"""
from __future__ import annotations

import zlib
from collections.abc import Sequence

import cv2
import numpy as np

from dope_hope.geometry import CENTROID_INDEX, CUBOID_EDGES, cuboid_keypoints, project_points

_SHIFT = 4                  # sub-pixel bits for OpenCV drawing
_LIMIT = 1 << 20            # coordinates are clipped to +-this before fixed-point conversion
#: Distinct colours for instances / classes (RGB).
PALETTE = ((255, 64, 64), (64, 255, 64), (64, 128, 255), (255, 220, 0), (255, 0, 255),
           (0, 230, 230), (255, 128, 0), (160, 80, 255))
#: Colours of the x, y, z axes (RGB: red, green, blue).
AXIS_COLORS = ((255, 0, 0), (0, 255, 0), (0, 0, 255))


def _fixed(p: np.ndarray) -> tuple[int, int]:
    q = np.clip(np.asarray(p, dtype=np.float64), -_LIMIT, _LIMIT)
    return int(round(q[0] * (1 << _SHIFT))), int(round(q[1] * (1 << _SHIFT)))


def _line(img: np.ndarray, a: np.ndarray, b: np.ndarray, color, thickness: int) -> None:
    if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
        cv2.line(img, _fixed(a), _fixed(b), tuple(int(c) for c in color), thickness, cv2.LINE_AA, _SHIFT)


def _circle(img: np.ndarray, p: np.ndarray, radius: float, color, thickness: int = -1) -> None:
    if np.all(np.isfinite(p)):
        cv2.circle(img, _fixed(p), int(round(radius * (1 << _SHIFT))), tuple(int(c) for c in color),
                   thickness, cv2.LINE_AA, _SHIFT)


def _scale(img: np.ndarray) -> float:
    """Line-width scale: 1 at 640 px on the longer side."""
    return max(img.shape[:2]) / 640.0


def draw_cuboid(image: np.ndarray, keypoints_2d: np.ndarray, color: Sequence[int] = (0, 255, 0),
                thickness: int | None = None, draw_points: bool = True) -> np.ndarray:
    """Draw a projected cuboid (12 edges, corners, centroid) on a copy of ``image``.

    Args:
        image: (H, W, 3) uint8 RGB.
        keypoints_2d: (9, 2) pixels in the documented order (8 corners, then the centre), or
            (8, 2) corners; NaN points and the edges touching them are skipped.
        color: RGB edge colour. The front face (corners 0-3, +z) is drawn with a thicker line,
            as in DOPE's visualizations, so that the box orientation is readable.
        thickness: line width in pixels (default: scaled with the image size).
        draw_points: draw the corners (numbered colour order) and the centroid.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    out = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    kp = np.asarray(keypoints_2d, dtype=np.float64).reshape(-1, 2)
    if thickness is None:
        thickness = max(1, int(round(2 * _scale(out))))
    for i, j in CUBOID_EDGES:
        front = i < 4 and j < 4
        _line(out, kp[i], kp[j], color, thickness + (1 if front else 0))
    if draw_points:
        r = max(1.5, 2.5 * _scale(out))
        for k in range(min(8, len(kp))):
            _circle(out, kp[k], r, PALETTE[k % len(PALETTE)])
        if len(kp) > CENTROID_INDEX:
            _circle(out, kp[CENTROID_INDEX], r, color)
    return out


def draw_axes(image: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, length: float = 0.05,
              thickness: int | None = None, origin: np.ndarray | None = None) -> np.ndarray:
    """Draw the x (red), y (green), z (blue) axes of a pose on a copy of ``image``.

    Args:
        image: (H, W, 3) uint8 RGB.
        K: (3, 3) intrinsics; R (3, 3), t (3,) metres: model -> camera.
        length: axis length, metres.
        origin: (3,) model-frame point the axes start from (default: the model origin).

    Returns:
        (H, W, 3) uint8 RGB. Axes behind the camera are not drawn.
    """
    out = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    pts = np.vstack([o, o + np.eye(3) * length])
    cam = pts @ np.asarray(R).T + np.asarray(t).reshape(1, 3)
    if np.any(cam[:, 2] <= 0):
        return out
    uv = project_points(cam, K)
    if thickness is None:
        thickness = max(1, int(round(2 * _scale(out))))
    for k in range(3):
        _line(out, uv[0], uv[k + 1], AXIS_COLORS[k], thickness)
    return out


def draw_keypoints(image: np.ndarray, keypoints_2d: np.ndarray, color: Sequence[int] = (255, 255, 0),
                   radius: float | None = None, labels: bool = False) -> np.ndarray:
    """Draw points (N, 2) (NaN skipped), optionally numbered, on a copy of ``image``."""
    out = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    kp = np.asarray(keypoints_2d, dtype=np.float64).reshape(-1, 2)
    r = radius if radius is not None else max(1.5, 2.5 * _scale(out))
    for k, p in enumerate(kp):
        _circle(out, p, r, color)
        if labels and np.all(np.isfinite(p)):
            cv2.putText(out, str(k), (int(p[0] + r + 1), int(p[1] - r - 1)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.35 * max(1.0, _scale(out)), tuple(int(c) for c in color), 1, cv2.LINE_AA)
    return out


def draw_label(image: np.ndarray, text: str, xy: tuple[int, int] = (4, 4),
               color: Sequence[int] = (255, 255, 255)) -> np.ndarray:
    """Text with a dark backing box, top-left corner at ``xy``, on a copy of ``image``."""
    out = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    scale = 0.4 * max(1.0, _scale(out))
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = xy
    cv2.rectangle(out, (x, y), (x + w + 4, y + h + base + 4), (0, 0, 0), -1)
    cv2.putText(out, text, (x + 2, y + h + 2), cv2.FONT_HERSHEY_SIMPLEX, scale,
                tuple(int(c) for c in color), 1, cv2.LINE_AA)
    return out


def montage(images: Sequence[np.ndarray], cols: int | None = None, tile_hw: tuple[int, int] | None = None,
            gap: int = 2, background: int = 32) -> np.ndarray:
    """Grid of RGB (or gray) images, each resized to ``tile_hw`` (default: the first's size).

    Returns:
        (rows * (h + gap) - gap, cols * (w + gap) - gap, 3) uint8.
    """
    if len(images) == 0:
        raise ValueError("montage of no images")
    imgs = [np.repeat(i[..., None], 3, axis=2) if i.ndim == 2 else i[..., :3] for i in images]
    h, w = tile_hw if tile_hw is not None else imgs[0].shape[:2]
    cols = cols or int(np.ceil(np.sqrt(len(imgs))))
    rows = int(np.ceil(len(imgs) / cols))
    out = np.full((rows * (h + gap) - gap, cols * (w + gap) - gap, 3), background, np.uint8)
    for n, img in enumerate(imgs):
        r, c = divmod(n, cols)
        tile = img if img.shape[:2] == (h, w) else cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        out[r * (h + gap): r * (h + gap) + h, c * (w + gap): c * (w + gap) + w] = tile.astype(np.uint8)
    return out


# ----------------------------------------------------------------------------- detections
def class_color(class_name: str) -> tuple[int, int, int]:
    """A stable RGB colour per class name (same in every process: CRC32, not ``hash``)."""
    return PALETTE[zlib.crc32(str(class_name).encode("utf-8")) % len(PALETTE)]


def overlay_detections(image: np.ndarray, detections: Sequence, K: np.ndarray,
                       axis_length: float | None = None, show_empty: bool = True) -> np.ndarray:
    """Projected cuboids, pose axes and "class score" labels of detections, on a copy of ``image``.

    Args:
        image: (H, W, 3) uint8 RGB (the original image the detections refer to).
        detections: objects with ``class_name``, ``score``, ``R`` (3, 3), ``t`` (3,) metres and
            either ``projected_2d`` (9, 2) px or ``cuboid_size_m`` (3,) (+ optional
            ``cuboid_center_m``), e.g. :class:`dope_hope.inference.predictor.Detection`; an optional
            ``ls_applied`` adds "LS" to the label, a ``track_id`` (tracked objects,
            :class:`dope_hope.inference.tracking.TrackedObject`) "#ID" after the class, and
            ``tracked == "coasted"`` the word "coasted".
        K: (3, 3) intrinsics of ``image``.
        axis_length: axis length in metres (default: half the largest cuboid extent, else 5 cm).
        show_empty: write "no detections" when the list is empty.

    Returns:
        (H, W, 3) uint8 RGB; one colour per class (:func:`class_color`).
    """
    out = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    H, W = out.shape[:2]
    for det in detections:
        color = class_color(det.class_name)
        size = getattr(det, "cuboid_size_m", None)
        center = getattr(det, "cuboid_center_m", None)
        kp = getattr(det, "projected_2d", None)
        if kp is None and size is not None:
            kp = project_points(cuboid_keypoints(size, center), K, det.R, det.t)
        if kp is not None:
            out = draw_cuboid(out, kp, color)
        length = axis_length if axis_length is not None else (
            0.5 * float(np.max(size)) if size is not None else 0.05)
        out = draw_axes(out, K, det.R, det.t, length=length, origin=center)
        track_id = getattr(det, "track_id", None)
        text = f"{det.class_name}" + (f" #{track_id}" if track_id is not None else "") + f" {det.score:.2f}" \
            + (" LS" if getattr(det, "ls_applied", False) else "") \
            + (" coasted" if getattr(det, "tracked", "detected") == "coasted" else "")
        anchor = np.array([4.0, 4.0])
        if kp is not None and np.isfinite(kp).all(axis=1).any():
            finite = np.asarray(kp)[np.isfinite(kp).all(axis=1)]
            anchor = np.array([finite[:, 0].min(), finite[:, 1].min() - 18 * max(1.0, _scale(out))])
        x = int(np.clip(anchor[0], 0, max(0, W - 60)))
        y = int(np.clip(anchor[1], 0, max(0, H - 16)))
        out = draw_label(out, text, (x, y), color)
    if show_empty and len(detections) == 0:
        out = draw_label(out, "no detections")
    return out


def belief_montage(belief: np.ndarray, image: np.ndarray | None = None,
                   names: Sequence[str] | None = None, cols: int = 3, max_side: int = 320,
                   alpha: float = 1.0, cmap: str = "inferno") -> np.ndarray:
    """Grid of belief maps, colour-mapped and (optionally) blended over the image.

    Args:
        belief: (C, h, w) maps (values clipped to [0, 1]) covering the same field of view as
            ``image`` (crop network padding first, e.g. with
            :meth:`dope_hope.inference.predictor.NetworkInput.maps_on_image`).
        image: optional (H, W, 3) uint8 RGB background (shown in gray).
        names: tile titles (default: "corner 0" .. "corner 7", "centroid" for 9 maps).
        cols: tiles per row. max_side: longer side of a tile, pixels.
        alpha: weight of the colour-mapped belief over the (dimmed) background where the
            belief is 1; the weight falls linearly to 0 with the belief.
        cmap: matplotlib colormap name.

    Returns:
        (rows * (th + 2) - 2, cols * (tw + 2) - 2, 3) uint8 RGB.
    """
    from matplotlib import colormaps  # noqa: PLC0415 (matplotlib (slow to import) only for the colour map)

    maps = np.clip(np.nan_to_num(np.asarray(belief, dtype=np.float32)), 0.0, 1.0)
    if maps.ndim != 3 or maps.shape[0] == 0:
        raise ValueError(f"belief must be (C, h, w), got shape {maps.shape}")
    ref_h, ref_w = image.shape[:2] if image is not None else maps.shape[1:]
    s = max_side / max(ref_h, ref_w)
    th, tw = max(1, round(ref_h * s)), max(1, round(ref_w * s))
    if names is None:
        names = ([f"corner {k}" for k in range(CENTROID_INDEX)] + ["centroid"]
                 if maps.shape[0] == CENTROID_INDEX + 1 else [str(k) for k in range(maps.shape[0])])
    background = None
    if image is not None:
        gray = cv2.cvtColor(np.ascontiguousarray(image[..., :3], dtype=np.uint8), cv2.COLOR_RGB2GRAY)
        gray = cv2.resize(gray, (tw, th), interpolation=cv2.INTER_AREA)
        background = np.repeat(gray[..., None], 3, axis=2).astype(np.float32)
    lut = colormaps[cmap]
    tiles = []
    for k, m in enumerate(maps):
        m = cv2.resize(m, (tw, th), interpolation=cv2.INTER_LINEAR)
        colored = lut(m)[..., :3].astype(np.float32) * 255.0
        if background is None:
            tile = colored
        else:  # the belief value is the blend weight: the image stays readable where it is 0
            w = (alpha * m)[..., None]
            tile = (1 - w) * (0.75 * background) + w * colored
        tile = np.clip(tile + 0.5, 0, 255).astype(np.uint8)
        tiles.append(draw_label(tile, f"{names[k]} max {float(maps[k].max()):.2f}"))
    return montage(tiles, cols=min(cols, len(tiles)))
