"""Table-top clutter backgrounds: a pile of shaded, textured boxes, cylinders, cards and blobs.

Drawn in 2D over a background (a photo crop or a procedural image) with OpenCV, no OpenGL:
each object is an orthographic view of a random box (its visible faces, texture warped onto
each, Lambert-shaded by the frame's one light direction), an upright cylinder turned in the
image plane (texture across the body, shading across its width, an elliptic top), a flat
card seen at an angle, or an elliptic blob, each with a soft drop shadow away from the
light. Objects lower in the image are drawn later and larger (nearer on the table). Their
textures are procedural images or, when photographs are given, crops of those ("photo-like").
"""
from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.config import SectionSettings
from dope_hope.synth.textures import procedural_image

#: Object kinds of a clutter pile.
CLUTTER_KINDS = ("box", "cylinder", "card", "blob")

#: (h, w, 3) float32 colours and (h, w) float32 coverage of one object on its own canvas.
Sprite = tuple[np.ndarray, np.ndarray]

_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
# Faces of the box: (axis, sign, 4 corner indices into _BOX_SIGNS in cyclic order).
_BOX_FACES = [(0, -1, (0, 1, 3, 2)), (0, 1, (4, 5, 7, 6)), (1, -1, (0, 1, 5, 4)),
              (1, 1, (2, 3, 7, 6)), (2, -1, (0, 2, 6, 4)), (2, 1, (1, 3, 7, 5))]


def _warp_to_quad(texture: np.ndarray, quad: np.ndarray, w: int, h: int) -> np.ndarray:
    """Texture (t, t, 3) mapped onto the parallelogram ``quad`` (4, 2) px of a (h, w) canvas."""
    t = texture.shape[0] - 1
    src = np.float32([[0, 0], [t, 0], [t, t]])
    M = cv2.getAffineTransform(src, np.float32(quad[:3]))
    return cv2.warpAffine(texture, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def box_sprite(rng: np.random.Generator, size_px: float, texture: Callable[[], np.ndarray],
               light: np.ndarray, ambient: float) -> Sprite:
    """A randomly turned box (extents 0.3-1 x ``size_px``), visible faces textured and shaded.

    ``light``: (3,) unit vector towards the light; shade = ambient + (1 - ambient) * max(0, n . light).
    """
    R = Rotation.random(random_state=rng).as_matrix()
    half = size_px * rng.uniform(0.3, 1.0, size=3) / 2.0
    pts = (_BOX_SIGNS * half) @ R.T                          # (8, 3), camera looks along +z
    side = int(np.ceil(2 * np.abs(pts[:, :2]).max())) + 3
    xy = pts[:, :2] + side / 2.0
    rgb = np.zeros((side, side, 3), np.float32)
    alpha = np.zeros((side, side), np.float32)
    tex = texture()                                          # one print on all faces
    for axis, sign, idx in _BOX_FACES:
        n = sign * R[:, axis]
        if n[2] >= -1e-3:                                    # faces away from the camera
            continue
        quad = xy[list(idx)]
        x0, y0 = np.floor(quad.min(axis=0)).astype(int)
        x1, y1 = np.ceil(quad.max(axis=0)).astype(int) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, side), min(y1, side)
        if x1 <= x0 or y1 <= y0:
            continue
        local = quad - (x0, y0)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, np.round(local * 16).astype(np.int32), 255, cv2.LINE_AA, shift=4)
        shade = ambient + (1.0 - ambient) * max(0.0, float(n @ light))
        face = _warp_to_quad(tex, local, x1 - x0, y1 - y0).astype(np.float32) * shade
        m = mask.astype(np.float32)[..., None] / 255.0
        rgb[y0:y1, x0:x1] = rgb[y0:y1, x0:x1] * (1 - m) + face * m
        alpha[y0:y1, x0:x1] = np.maximum(alpha[y0:y1, x0:x1], m[..., 0])
    return rgb, alpha


def _rotate_sprite(rgb: np.ndarray, alpha: np.ndarray, angle_deg: float) -> Sprite:
    h, w = alpha.shape
    side = int(np.ceil(np.hypot(h, w))) + 2
    M = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), angle_deg, 1.0)
    M[:, 2] += ((side - w) / 2.0, (side - h) / 2.0)
    return (cv2.warpAffine(rgb, M, (side, side), flags=cv2.INTER_LINEAR),
            cv2.warpAffine(alpha, M, (side, side), flags=cv2.INTER_LINEAR))


def cylinder_sprite(rng: np.random.Generator, size_px: float, texture: Callable[[], np.ndarray],
                    light: np.ndarray, ambient: float) -> Sprite:
    """An upright can / bottle body with an elliptic top, turned up to 40 degrees in the image."""
    h = max(4, int(size_px * rng.uniform(0.5, 1.0)))
    w = max(4, int(h * rng.uniform(0.3, 0.9)))
    e = max(1, int(w * rng.uniform(0.1, 0.35) / 2))          # half-height of the top ellipse
    H = h + 2 * e
    tex = cv2.resize(texture(), (w, H), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    x = (np.arange(w, dtype=np.float32) + 0.5) / w * 2.0 - 1.0
    normal_x, normal_z = x, -np.sqrt(np.clip(1.0 - x * x, 0.0, 1.0))
    lam = np.maximum(0.0, normal_x * light[0] + normal_z * light[2])
    shade = (ambient + (1.0 - ambient) * lam)[None, :, None]
    body = np.zeros((H, w), np.uint8)
    cv2.rectangle(body, (0, e), (w - 1, H - 1 - e), 255, -1)
    cv2.ellipse(body, (w // 2, H - 1 - e), (w // 2, e), 0, 0, 180, 255, -1, cv2.LINE_AA)
    top = np.zeros((H, w), np.uint8)
    cv2.ellipse(top, (w // 2, e), (w // 2, e), 0, 0, 360, 255, -1, cv2.LINE_AA)
    top_shade = ambient + (1.0 - ambient) * max(0.0, -float(light[1]))  # the top faces -y (up)
    mb, mt = body.astype(np.float32)[..., None] / 255.0, top.astype(np.float32)[..., None] / 255.0
    rgb = tex * shade * mb
    rgb = rgb * (1 - mt) + tex[::-1] * top_shade * mt
    alpha = np.maximum(mb, mt)[..., 0]
    return _rotate_sprite(rgb, alpha, rng.uniform(-40.0, 40.0))


def card_sprite(rng: np.random.Generator, size_px: float, texture: Callable[[], np.ndarray],
                light: np.ndarray, ambient: float) -> Sprite:
    """A flat card, book or sheet seen at an angle (a random parallelogram), uniformly shaded."""
    side = max(4, int(size_px)) + 2
    c = side / 2.0
    a = rng.uniform(0, 2 * np.pi)
    u = np.array([np.cos(a), np.sin(a)]) * size_px * rng.uniform(0.25, 0.5)
    b = a + rng.uniform(0.4, 2.7)
    v = np.array([np.cos(b), np.sin(b)]) * size_px * rng.uniform(0.15, 0.5)
    quad = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
    mask = np.zeros((side, side), np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad * 16).astype(np.int32), 255, cv2.LINE_AA, shift=4)
    shade = ambient + (1.0 - ambient) * rng.uniform(0.3, 1.0)
    m = mask.astype(np.float32)[..., None] / 255.0
    return _warp_to_quad(texture(), quad, side, side).astype(np.float32) * shade * m, m[..., 0]


def blob_sprite(rng: np.random.Generator, size_px: float, texture: Callable[[], np.ndarray],
                light: np.ndarray, ambient: float) -> Sprite:
    """An ellipse shaded as a dome lit from ``light`` (a ball, a lid, a crumpled bag)."""
    side = max(4, int(size_px)) + 2
    ax = (max(1, int(side * rng.uniform(0.2, 0.49))), max(1, int(side * rng.uniform(0.15, 0.49))))
    angle = rng.uniform(0, 180)
    mask = np.zeros((side, side), np.uint8)
    cv2.ellipse(mask, (side // 2, side // 2), ax, angle, 0, 360, 255, -1, cv2.LINE_AA)
    yy, xx = (np.mgrid[0:side, 0:side].astype(np.float32) - side / 2.0) / (side / 2.0)
    nz = -np.sqrt(np.clip(1.0 - xx * xx - yy * yy, 0.0, 1.0))
    lam = np.maximum(0.0, xx * light[0] + yy * light[1] + nz * light[2])
    shade = (ambient + (1.0 - ambient) * lam)[..., None]
    tex = cv2.resize(texture(), (side, side), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    m = mask.astype(np.float32)[..., None] / 255.0
    return tex * shade * m, m[..., 0]


_SPRITES = {"box": box_sprite, "cylinder": cylinder_sprite, "card": card_sprite, "blob": blob_sprite}


def _paste(acc: np.ndarray, trans: np.ndarray, rgb: np.ndarray, alpha: np.ndarray, x0: int, y0: int,
           shadow: float = 0.0) -> None:
    """Draw a sprite (premultiplied ``rgb``, ``alpha``) at (x0, y0), clipped, into the layer
    ``acc`` (H, W, 3) premultiplied colours and ``trans`` (H, W, 1) transmittance of the
    background; with ``shadow`` > 0 the sprite only darkens both by ``shadow * alpha``."""
    H, W = trans.shape[:2]
    h, w = alpha.shape
    u0, v0, u1, v1 = max(x0, 0), max(y0, 0), min(x0 + w, W), min(y0 + h, H)
    if u1 <= u0 or v1 <= v0:
        return
    a = alpha[v0 - y0:v1 - y0, u0 - x0:u1 - x0, None]
    keep = 1.0 - (shadow * a if shadow > 0 else a)
    acc[v0:v1, u0:u1] *= keep
    trans[v0:v1, u0:u1] *= keep
    if shadow <= 0:
        acc[v0:v1, u0:u1] += rgb[v0 - y0:v1 - y0, u0 - x0:u1 - x0]


def clutter_image(rng: np.random.Generator, base: np.ndarray, cfg: SectionSettings,
                  texture_source: Callable[[np.random.Generator, int], np.ndarray] | None = None) -> np.ndarray:
    """A pile of clutter drawn over ``base`` (module docstring).

    The pile is drawn at ``cfg.resolution`` times the image size (premultiplied colours and
    the background's transmittance), upsampled and laid over the full-resolution ``base``.

    Args:
        rng: the frame's generator for the clutter.
        base: (H, W, 3) uint8 background under the pile.
        cfg: the ``background.clutter`` section of the synth config.
        texture_source: (rng, px) -> (px, px, 3) uint8 texture cut from photographs, used
            with ``photo_texture_prob`` (None: procedural textures only).

    Returns:
        (H, W, 3) uint8.
    """
    H, W = base.shape[:2]
    f = float(cfg.resolution)
    h, w = max(1, int(round(H * f))), max(1, int(round(W * f)))
    diag = float(np.hypot(w, h))
    acc = np.zeros((h, w, 3), np.float32)
    trans = np.ones((h, w, 1), np.float32)
    # unit vector towards the light (camera frame: x right, y down, z forward), from the
    # camera's side and mostly from above
    light = np.array([rng.uniform(-0.7, 0.7), rng.uniform(-0.9, 0.2), -1.0])
    light /= np.linalg.norm(light)
    ambient = float(rng.uniform(*cfg.ambient))
    px = int(cfg.texture_px)
    weights = cfg.kinds.to_dict()  # kind -> weight
    kinds = [k for k in CLUTTER_KINDS if float(weights.get(k, 0.0)) > 0]
    p = np.array([float(weights[k]) for k in kinds])
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    ys = np.sort(rng.uniform(-0.1, 1.1, size=n))             # back (top) to front (bottom)

    pool = []
    for _ in range(int(cfg.texture_pool)):
        photo = texture_source is not None and rng.random() < cfg.photo_texture_prob
        pool.append(texture_source(rng, px) if photo else procedural_image(rng, px, px))

    def texture() -> np.ndarray:  # a texture of the pool, turned, with its own colour gain
        t = np.rot90(pool[int(rng.integers(0, len(pool)))], int(rng.integers(0, 4)))
        gain = rng.uniform(0.6, 1.25, size=3).astype(np.float32)
        return np.clip(t.astype(np.float32) * gain, 0, 255).astype(np.uint8)

    shadow_dx, shadow_dy = -light[0], -light[1]             # shadows fall away from the light
    for y in ys:
        kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
        size = diag * rng.uniform(*cfg.size) * (0.6 + 0.6 * float(np.clip(y, 0.0, 1.0)))
        rgb, alpha = _SPRITES[kind](rng, size, texture, light, ambient)
        sh, sw = alpha.shape
        x0 = int(rng.uniform(-0.1, 1.1) * w - sw / 2)
        y0 = int(y * h - sh / 2)
        if rng.random() < cfg.shadow_prob:
            sigma = max(0.7, 0.06 * size)
            pad = int(3 * sigma)
            soft = cv2.GaussianBlur(np.pad(alpha, pad), (0, 0), sigma)
            off = 0.12 * size
            _paste(acc, trans, rgb, soft, x0 - pad + int(off * shadow_dx), y0 - pad + int(off * shadow_dy),
                   shadow=float(rng.uniform(0.3, 0.7)))
        _paste(acc, trans, rgb, alpha, x0, y0)
    sigma = rng.uniform(*cfg.blur_sigma_px)
    if (h, w) != (H, W):
        acc = cv2.resize(acc, (W, H), interpolation=cv2.INTER_LINEAR)
        trans = cv2.resize(trans, (W, H), interpolation=cv2.INTER_LINEAR)[..., None]
    img = base.astype(np.float32) * trans + acc
    if sigma > 0.3:
        img = cv2.GaussianBlur(img, (0, 0), float(sigma))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
