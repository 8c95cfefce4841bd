"""Procedural images: value noise, gradients, random shapes, stripes and checkers.

They serve as backgrounds (when no photographs are given) and as distractor textures. Every
function takes a ``numpy.random.Generator`` and returns an (H, W, 3) uint8 RGB image; the
same generator state gives the same image.
"""
from __future__ import annotations

import cv2
import numpy as np

#: Procedural kinds understood by :func:`procedural_image`.
PROCEDURAL_KINDS = ("noise", "gradient", "shapes", "stripes", "checker")


def random_color(rng: np.random.Generator, saturation: tuple[float, float] = (0.0, 1.0),
                 value: tuple[float, float] = (0.1, 1.0)) -> np.ndarray:
    """(3,) float RGB in [0, 1] from a uniform hue and the given saturation/value ranges."""
    hsv = np.array([[[rng.uniform(0.0, 180.0), 255.0 * rng.uniform(*saturation),
                      255.0 * rng.uniform(*value)]]], dtype=np.float32)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0].astype(np.float64) / 255.0


def value_noise(rng: np.random.Generator, height: int, width: int, octaves: int = 4,
                base_cells: int = 4) -> np.ndarray:
    """(H, W) float32 fractal value noise in [0, 1]: random grids upsampled bicubically.

    OpenCV's resize does the interpolation; octave k has ``base_cells * 2**k`` cells along the
    longer side and half the amplitude of octave k - 1.
    """
    out = np.zeros((height, width), np.float32)
    amp, total = 1.0, 0.0
    longer = max(height, width)
    for k in range(octaves):
        cells = max(2, base_cells * 2**k)
        gh = max(2, int(round(cells * height / longer)))
        gw = max(2, int(round(cells * width / longer)))
        grid = rng.random((gh, gw), dtype=np.float32)
        out += amp * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
    out /= total
    lo, hi = float(out.min()), float(out.max())
    return (out - lo) / max(hi - lo, 1e-6)


def _colorize(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """Map a (H, W) field in [0, 1] to RGB between two random colours -> (H, W, 3) uint8."""
    c0 = (random_color(rng) * 255.0).astype(np.float32)
    c1 = (random_color(rng) * 255.0).astype(np.float32)
    t = np.asarray(t, dtype=np.float32)[..., None]
    rgb = c0 + (c1 - c0) * t
    return np.clip(rgb + 0.5, 0, 255).astype(np.uint8)


def noise_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Coloured fractal noise, (H, W, 3) uint8."""
    octaves = int(rng.integers(2, 6))
    base = int(rng.integers(2, 9))
    return _colorize(rng, value_noise(rng, height, width, octaves=octaves, base_cells=base))


def gradient_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Linear or radial gradient between two random colours, (H, W, 3) uint8."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    xx /= max(width - 1, 1)
    yy /= max(height - 1, 1)
    if rng.random() < 0.5:
        angle = rng.uniform(0.0, 2.0 * np.pi)
        t = np.cos(angle) * xx + np.sin(angle) * yy
    else:
        cx, cy = rng.uniform(0.0, 1.0, size=2)
        t = np.hypot(xx - cx, yy - cy)
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    return _colorize(rng, t)


def shapes_image(rng: np.random.Generator, height: int, width: int,
                 count: tuple[int, int] = (5, 40)) -> np.ndarray:
    """Random filled rectangles, circles, ellipses, polygons and lines over a gradient."""
    img = np.ascontiguousarray(gradient_image(rng, height, width))
    scale = max(height, width)
    for _ in range(int(rng.integers(count[0], count[1] + 1))):
        color = tuple(int(c) for c in (random_color(rng) * 255.0))
        kind = int(rng.integers(0, 5))
        p = rng.uniform(0, 1, size=2) * (width, height)
        r = rng.uniform(0.02, 0.3) * scale
        if kind == 0:
            q = p + rng.uniform(-1, 1, size=2) * r * 2
            cv2.rectangle(img, tuple(int(v) for v in p), tuple(int(v) for v in q), color, -1)
        elif kind == 1:
            cv2.circle(img, tuple(int(v) for v in p), int(r), color, -1, cv2.LINE_AA)
        elif kind == 2:
            axes = (int(r), int(r * rng.uniform(0.2, 1.0)))
            cv2.ellipse(img, tuple(int(v) for v in p), axes, rng.uniform(0, 180), 0, 360, color, -1,
                        cv2.LINE_AA)
        elif kind == 3:
            n = int(rng.integers(3, 7))
            pts = (p + rng.uniform(-1, 1, size=(n, 2)) * r).astype(np.int32)
            cv2.fillPoly(img, [pts], color, cv2.LINE_AA)
        else:
            q = p + rng.uniform(-1, 1, size=2) * r * 3
            thickness = int(max(1, rng.uniform(0.002, 0.02) * scale))
            cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), color, thickness,
                     cv2.LINE_AA)
    return img


def stripes_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Sine or square stripes at a random angle and frequency, (H, W, 3) uint8."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    angle = rng.uniform(0.0, np.pi)
    period = rng.uniform(0.02, 0.25) * max(height, width)
    phase = (np.cos(angle) * xx + np.sin(angle) * yy) / period * 2.0 * np.pi
    t = 0.5 + 0.5 * np.sin(phase)
    if rng.random() < 0.5:
        t = (t > 0.5).astype(np.float32)
    return _colorize(rng, t)


def checker_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Checkerboard with a random cell size, (H, W, 3) uint8."""
    cell = max(2, int(rng.uniform(0.03, 0.25) * max(height, width)))
    yy, xx = np.mgrid[0:height, 0:width]
    t = (((xx // cell) + (yy // cell)) % 2).astype(np.float32)
    return _colorize(rng, t)


_MAKERS = {
    "noise": noise_image,
    "gradient": gradient_image,
    "shapes": shapes_image,
    "stripes": stripes_image,
    "checker": checker_image,
}


def procedural_image(rng: np.random.Generator, height: int, width: int,
                     weights: dict[str, float] | None = None) -> np.ndarray:
    """One procedural image of a kind drawn with ``weights`` (kind -> weight; default uniform).

    Returns:
        (H, W, 3) uint8 RGB.
    """
    weights = weights or {k: 1.0 for k in PROCEDURAL_KINDS}
    kinds = [k for k in PROCEDURAL_KINDS if weights.get(k, 0.0) > 0.0]
    if not kinds:
        raise ValueError("procedural image weights are all zero")
    p = np.array([weights[k] for k in kinds], dtype=np.float64)
    kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
    return _MAKERS[kind](rng, height, width)


#: OpenCV's Hershey fonts (the only ones it draws without a font file).
_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_COMPLEX_SMALL,
          cv2.FONT_HERSHEY_SCRIPT_SIMPLEX)
_LETTERS = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789"))


def _random_word(rng: np.random.Generator, n: tuple[int, int] = (3, 10)) -> str:
    return "".join(rng.choice(_LETTERS, size=int(rng.integers(n[0], n[1] + 1))))


def _put_text_fitted(img: np.ndarray, text: str, center: tuple[float, float], width_px: float,
                     font: int, color: tuple[int, ...], thickness: int) -> None:
    """Draw ``text`` centred on ``center`` at the font scale that makes it ``width_px`` wide."""
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, thickness)
    scale = max(0.2, width_px / max(tw, 1))
    (tw, th), _ = cv2.getTextSize(text, font, scale, thickness)
    org = (int(center[0] - tw / 2), int(center[1] + th / 2))
    cv2.putText(img, text, org, font, scale, color, thickness, cv2.LINE_AA)


def label_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A packaging-like texture: coloured bands, a brand word, a logo, lines of small print and
    sometimes a barcode or a picture-like noise patch over a plain or gradient ground.

    Grocery packaging is what the HOPE objects wear; OpenCV draws it (Hershey fonts), so no
    font or image file is needed. Returns (H, W, 3) uint8 RGB.
    """
    img = np.ascontiguousarray(gradient_image(rng, height, width) if rng.random() < 0.5 else
                               np.broadcast_to((random_color(rng) * 255).astype(np.uint8),
                                               (height, width, 3)).copy())
    scale = min(height, width)

    def color() -> tuple[int, int, int]:
        return tuple(int(c) for c in random_color(rng) * 255.0)

    for _ in range(int(rng.integers(0, 4))):                          # horizontal bands
        y0 = rng.uniform(0, height)
        h = rng.uniform(0.03, 0.25) * height
        cv2.rectangle(img, (0, int(y0)), (width, int(y0 + h)), color(), -1)
    if rng.random() < 0.4:                                           # a picture-like patch
        ph, pw = int(rng.uniform(0.2, 0.5) * height), int(rng.uniform(0.2, 0.6) * width)
        y, x = int(rng.uniform(0, height - ph)), int(rng.uniform(0, width - pw))
        img[y:y + ph, x:x + pw] = noise_image(rng, ph, pw)
    for _ in range(int(rng.integers(0, 3))):                          # logos
        p = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
        r = int(rng.uniform(0.05, 0.2) * scale)
        if rng.random() < 0.5:
            cv2.circle(img, p, r, color(), -1, cv2.LINE_AA)
        else:
            cv2.ellipse(img, p, (r, int(r * rng.uniform(0.3, 1.0))), rng.uniform(0, 180), 0, 360,
                        color(), -1, cv2.LINE_AA)
    for _ in range(int(rng.integers(1, 3))):                          # brand words
        font = _FONTS[int(rng.integers(0, len(_FONTS)))]
        _put_text_fitted(img, _random_word(rng), (rng.uniform(0.3, 0.7) * width, rng.uniform(0.15, 0.85) * height),
                         rng.uniform(0.4, 0.9) * width, font, color(), int(rng.integers(1, 4)))
    ink = color()
    y = rng.uniform(0.5, 0.8) * height                               # small print
    for _ in range(int(rng.integers(0, 8))):
        x0 = rng.uniform(0.02, 0.3) * width
        _put_text_fitted(img, " ".join(_random_word(rng, (2, 7)) for _ in range(3)),
                         (x0 + 0.3 * width, y), rng.uniform(0.3, 0.6) * width, cv2.FONT_HERSHEY_PLAIN, ink, 1)
        y += rng.uniform(0.03, 0.06) * height
    if rng.random() < 0.3:                                           # barcode
        bw, bh = int(rng.uniform(0.15, 0.3) * width), int(rng.uniform(0.08, 0.15) * height)
        x, y = int(rng.uniform(0, width - bw)), int(rng.uniform(0, height - bh))
        img[y:y + bh, x:x + bw] = 255
        bars = rng.random(bw) < 0.45
        img[y + 1:y + bh - 1, x:x + bw][:, bars] = 0
    return img
