"""Hard negatives: distractors with the target's size, shape class and colours, not its texture.

:class:`TargetLook` summarizes the target once (cuboid extents, shape class from how much of
its cuboid the convex hull fills, colours sampled over its surface, its texture);
:func:`hard_negative_geometry` and :func:`hard_negative_material` make one look-alike from it.
Scene placement and seg ids are :func:`dope_hope.synth.scene.sample_hard_negatives`'s (role
"hard_negative", seg ids in the distractors' range; never annotated).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from dope_hope.config import SectionSettings
from dope_hope.synth.primitives import make_primitive
from dope_hope.synth.textures import procedural_image

#: Shape classes of a target (and of its look-alikes).
SHAPE_CLASSES = ("box", "cylinder", "bottle")
#: Texture kinds of a look-alike: a procedural pattern in the target's colours, the target's
#: texture cut into tiles and shuffled, or one of its colours.
TEXTURE_KINDS = ("palette", "shuffled", "flat")
#: Side of the target texture kept for shuffling, pixels.
LOOK_TEXTURE_PX = 256


def shape_class(mesh: trimesh.Trimesh, size: np.ndarray) -> str:
    """"box" when the convex hull fills >= 90 % of the cuboid, "cylinder" >= 70 % (a cylinder
    fills pi/4), else "bottle"."""
    try:
        fill = float(mesh.convex_hull.volume) / float(np.prod(size))
    except Exception:  # degenerate hull (flat mesh): treat as a box
        return "box"
    if fill >= 0.9:
        return "box"
    return "cylinder" if fill >= 0.7 else "bottle"


def surface_colors(mesh: trimesh.Trimesh, texture: np.ndarray | None, colors: np.ndarray | None,
                   count: int = 4096) -> np.ndarray:
    """(N, 3) uint8 colours at ``count`` area-weighted random points of the surface.

    Texture lookups at the points' uv (OpenGL convention, v up, wrapped); else vertex colours
    of the faces' first vertices; else mid grey. Fixed seed: a property of the mesh.
    """
    rng = np.random.default_rng(0)
    faces = np.asarray(mesh.faces)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    p = area / area.sum() if area.sum() > 0 else None
    f = rng.choice(len(faces), size=count, p=p)
    uv = getattr(mesh.visual, "uv", None)
    if texture is not None and uv is not None and len(uv) == len(mesh.vertices):
        b = rng.dirichlet(np.ones(3), size=count)                       # barycentric weights
        pts = np.einsum("nk,nkj->nj", b, np.asarray(uv, dtype=np.float64)[faces[f]]) % 1.0
        h, w = texture.shape[:2]
        x = np.clip((pts[:, 0] * w).astype(int), 0, w - 1)
        y = np.clip(((1.0 - pts[:, 1]) * h).astype(int), 0, h - 1)
        return np.ascontiguousarray(texture[y, x, :3], dtype=np.uint8)
    if colors is not None:
        return np.ascontiguousarray(colors[faces[f, 0], :3], dtype=np.uint8)
    return np.full((count, 3), 128, np.uint8)


@dataclass
class TargetLook:
    """What a look-alike copies from the target.

    Attributes:
        size: (3,) cuboid extents, metres.
        shape: one of :data:`SHAPE_CLASSES`.
        colors: (N, 3) uint8 colours sampled over its surface.
        texture: (h, w, 3) uint8, its texture at most :data:`LOOK_TEXTURE_PX` a side, or None.
    """

    size: np.ndarray
    shape: str
    colors: np.ndarray
    texture: np.ndarray | None

    @classmethod
    def of(cls, mesh: trimesh.Trimesh, texture: np.ndarray | None, colors: np.ndarray | None,
           size: np.ndarray) -> TargetLook:
        """From a mesh (metres), its texture / vertex colours and its cuboid extents."""
        small = None
        if texture is not None:
            small = np.ascontiguousarray(texture[..., :3])
            if max(small.shape[:2]) > LOOK_TEXTURE_PX:
                f = LOOK_TEXTURE_PX / max(small.shape[:2])
                small = cv2.resize(small, (max(1, int(small.shape[1] * f)), max(1, int(small.shape[0] * f))),
                                   interpolation=cv2.INTER_AREA)
        return cls(size=np.asarray(size, dtype=np.float64), shape=shape_class(mesh, size),
                   colors=surface_colors(mesh, texture, colors), texture=small)


def palette_texture(rng: np.random.Generator, look: TargetLook, px: int) -> np.ndarray:
    """A procedural pattern recoloured with 2-5 of the target's colours, (px, px, 3) uint8."""
    grey = cv2.cvtColor(procedural_image(rng, px, px), cv2.COLOR_RGB2GRAY).astype(np.float32)
    k = int(rng.integers(2, 6))
    edges = np.quantile(grey, np.linspace(0, 1, k + 1)[1:-1])
    level = np.searchsorted(edges, grey)
    palette = look.colors[rng.integers(0, len(look.colors), size=k)]
    return np.ascontiguousarray(palette[level])


def shuffled_texture(rng: np.random.Generator, look: TargetLook, px: int,
                     grid: tuple[int, int]) -> np.ndarray:
    """The target's texture resized to (px, px), cut into g x g tiles (g in ``grid``), the
    tiles permuted, rotated by multiples of 90 degrees and flipped at random. (px, px, 3) uint8."""
    g = int(rng.integers(grid[0], grid[1] + 1))
    tile = max(1, px // g)
    side = tile * g
    img = cv2.resize(look.texture, (side, side), interpolation=cv2.INTER_AREA)
    tiles = [img[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile] for r in range(g) for c in range(g)]
    order = rng.permutation(len(tiles))
    rots, flips = rng.integers(0, 4, size=len(tiles)), rng.random(len(tiles)) < 0.5
    out = np.empty_like(img)
    for j, i in enumerate(order):
        t = np.rot90(tiles[i], int(rots[j]))
        if flips[j]:
            t = t[:, ::-1]
        r, c = divmod(j, g)
        out[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile] = t
    return out if side == px else cv2.resize(out, (px, px), interpolation=cv2.INTER_NEAREST)


def hard_negative_geometry(rng: np.random.Generator, look: TargetLook, cfg: SectionSettings) -> trimesh.Trimesh:
    """A box, cylinder or bottle (the target's class with ``same_shape_prob``) the size of the
    target's cuboid, each extent scaled by ``size_jitter``; centred at the origin, with uv."""
    same = rng.random() < cfg.same_shape_prob
    kind = look.shape if same else SHAPE_CLASSES[int(rng.integers(0, len(SHAPE_CLASSES)))]
    s = np.sort(look.size)[::-1] * rng.uniform(*cfg.size_jitter, size=3)  # long, mid, short
    if kind == "box":
        dims = rng.permutation(s)
    else:  # axis along the longest extent, diameter the mean of the other two
        dims = np.array([(s[1] + s[2]) / 4.0, s[0]])
    return make_primitive(kind, dims, tile_m=float(max(look.size.max(), 1e-3)))


def hard_negative_material(rng: np.random.Generator, look: TargetLook,
                           cfg: SectionSettings) -> tuple[np.ndarray, np.ndarray | None]:
    """(base colour (4,) in [0, 1], texture (px, px, 3) uint8 or None) of one look-alike."""
    weights = {k: float(cfg.textures.to_dict().get(k, 0.0)) for k in TEXTURE_KINDS}
    if look.texture is None:
        weights["shuffled"] = 0.0
    if not any(v > 0 for v in weights.values()):
        weights["palette"] = 1.0
    keys = [k for k in TEXTURE_KINDS if weights[k] > 0]
    p = np.array([weights[k] for k in keys])
    kind = keys[int(rng.choice(len(keys), p=p / p.sum()))]
    px = int(cfg.texture_px)
    if kind == "palette":
        return np.ones(4), palette_texture(rng, look, px)
    if kind == "shuffled":
        return np.ones(4), shuffled_texture(rng, look, px, tuple(cfg.shuffle_grid))
    c = look.colors[int(rng.integers(0, len(look.colors)))].astype(np.float64) / 255.0
    return np.append(c, 1.0), None
