"""Appearance check: does a detected cuboid hold this mesh's object, and which of its
symmetric-equivalent poses, and which turn about its up axis, does the texture say?

A detector of a cuboid (the pretrained start, :mod:`dope_hope.inference.mesh_start`) finds
every object of that shape, and its pose only up to the cuboid's symmetries; and the start
learned cans and bottles with category-canonical labels (a can has no front), so for an
object it never saw it places the up axis far better than the turn about it (on the held-out
Ketchup frames, two thirds of the poses within 10 cm but not 2 cm were off mainly by a turn
about the bottle's axis). For each candidate pose, :class:`AppearanceCheck` renders the
textured mesh unlit (:class:`~dope_hope.render.textured.TexturedRenderer`) at each pose
``R S`` into a small square crop around the object and compares it with the same crop of
the image inside the rendered silhouette. The rotations ``S`` (about the cuboid centre,
:func:`candidate_rotations`) are the cuboid's symmetries, then (``spin_step_deg`` > 0) the
turns about the up axis in steps of ``spin_step_deg``, upright and upside down. The
comparison:

- texture: normalized cross-correlation of the colour channels (each channel's mean
  removed; invariant to gain and offset, so to most of the lighting);
- colour: intersection of the normalized-chromaticity histograms (r, g = R, G over R + G + B;
  invariant to the brightness).

The score is their mean, in [0, 1] (a negative correlation counts as 0); a detection whose
best pose scores under ``min_score`` is a look-alike, dropped. Which pose (``texture_features``,
the default, where the caller gives the network's first layers:
:meth:`dope_hope.inference.backends.TorchBackend.texture_features`): the one whose render
the network's stride-4 features find most like the image (:func:`feature_similarity`, the
mean cosine over the cells inside the silhouette); those features were trained on thousands of
textured objects and tell a label's side where the colour channels' correlation sees a red
bottle either way (on the held-out Ketchup frames, of the 65 detections that one of the 24
rotations puts within 2 cm, they choose such a rotation for 52, the colour score for 35).
Without them, the colour score chooses. The chosen pose replaces the detection's; poses
scoring within ``ambiguity_margin`` of it remain ambiguous. CPU cost: one render of
``crop_px`` squared pixels per rotation (5-10 ms each at 64 px on 2 cores, Mesa llvmpipe):
4 for a box of three different extents without turns, 24 with the default 30° turns; the
features of all of them, one batch (~7 ms for 25 crops).

What the mesh's surface shows decides what can be compared (:func:`surface_appearance`): a
texture image or colours that vary tell poses apart; one colour tells a look-alike of another
colour, never one pose from another (the check then compares the candidate's own pose alone,
by the colour histograms, and resolves nothing); a mesh with no texture and no colours
(trimesh's default grey) has nothing to compare, and :class:`AppearanceCheck` refuses it.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.config import SectionSettings, at_least, boolean, finite_float, nonnegative_float
from dope_hope.errors import ConfigError
from dope_hope.geometry import project_points

#: Two candidate rotations closer than this (Frobenius norm of the difference) are one.
_SAME_ROTATION = 1e-6
#: Colours whose spread (standard deviation of a channel, 0-255 levels) stays under this are one colour.
UNIFORM_COLOUR_STD = 2.0
#: A texture image is judged from a copy this many pixels on a side (its mean colours kept).
_TEXTURE_PREVIEW_PX = 128


def _spin_step(value, name: str) -> float:
    """The rule of ``spin_step_deg``: 0 (no turns) or a step in (0, 180] degrees."""
    v = nonnegative_float(value, name)
    if v > 180:
        raise ConfigError(f"{name} must be 0 (no turns) or a step in (0, 180] degrees, got {value!r}")
    return v


def _refine_step(value, name: str) -> float:
    """The rule of ``trained_refine_deg``: 0 (no refinement) or a step in (0, 45] degrees."""
    v = nonnegative_float(value, name)
    if v > 45:
        raise ConfigError(f"{name} must be 0 (no refinement) or a step in (0, 45] degrees, got {value!r}")
    return v


@dataclass(frozen=True)
class AppearanceSettings(SectionSettings):
    """The appearance check's settings (``appearance:`` in ``dope_hope/configs/infer.yaml``;
    :class:`AppearanceCheck`).

    enabled: false turns the check off (every cuboid of the mesh's shape is reported, its pose
    known up to the cuboid's symmetries). crop_px: side of the compared crops, pixels.
    margin: the crop's border around the object's projected box, a fraction of its larger side. min_score: detections scoring
    lower are dropped (0 keeps all). ambiguity_margin: poses scoring within this of the best
    stay ambiguous. min_pixels: fewer silhouette pixels in the crop score 0. hist_bins:
    chromaticity histogram bins per axis. spin_step_deg: the turns about the up axis
    compared besides the cuboid's symmetries, degrees apart (0: the symmetries alone).
    texture_features: the pose is the one the network's first layers find most like the image
    (false: the one the colour score prefers). trained_turns: a trained model's poses are
    turned too, about each textured object's long axis (:mod:`dope_hope.inference.turns`; off:
    a render per turn and detection). trained_refine_deg: after that turn, the pose tilted and
    turned by this many degrees either way about each mesh axis is compared too, once (0: not)."""

    SECTION = "appearance"
    RULES = {"enabled": boolean, "crop_px": at_least(8), "margin": nonnegative_float, "min_score": finite_float,
             "ambiguity_margin": nonnegative_float, "min_pixels": at_least(1), "hist_bins": at_least(1),
             "spin_step_deg": _spin_step, "texture_features": boolean,
             "trained_turns": boolean, "trained_refine_deg": _refine_step}

    enabled: bool = True
    crop_px: int = 64
    margin: float = 0.15
    min_score: float = 0.25
    ambiguity_margin: float = 0.03
    min_pixels: int = 30
    hist_bins: int = 8
    spin_step_deg: float = 30.0
    texture_features: bool = True
    trained_turns: bool = False
    trained_refine_deg: float = 8.0


def candidate_rotations(symmetries: np.ndarray, up: np.ndarray | None, spin_step_deg: float,
                        upside_down: bool = True) -> np.ndarray:
    """(S', 3, 3) the rotations the check compares, mesh frame, about the cuboid centre:
    ``symmetries`` (S, 3, 3) first (identity first, as given), then the turns about the unit
    axis ``up`` (3,) by every multiple of ``spin_step_deg`` below 360°, each also after a half
    turn about an axis across ``up`` (upside down; ``upside_down`` False: not), those equal to
    an earlier one left out. ``up`` None or a step of 0: the symmetries alone."""
    out = [np.asarray(S, dtype=np.float64) for S in np.asarray(symmetries, dtype=np.float64).reshape(-1, 3, 3)]
    if up is None or spin_step_deg <= 0:
        return np.stack(out)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    up = up / np.linalg.norm(up)
    across = np.roll(np.abs(up), 1)  # a mesh axis across an axis-aligned up (any axis across it otherwise)
    across = across - (across @ up) * up
    if np.linalg.norm(across) < 1e-9:
        across = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    flip = Rotation.from_rotvec(np.pi * across / np.linalg.norm(across)).as_matrix()
    for upside in (np.eye(3), flip) if upside_down else (np.eye(3),):
        for angle in np.arange(0.0, 360.0 - 1e-9, spin_step_deg):
            S = upside @ Rotation.from_rotvec(np.radians(angle) * up).as_matrix()
            if all(np.linalg.norm(S - T) > _SAME_ROTATION for T in out):
                out.append(S)
    return np.stack(out)


def _spread(colours: np.ndarray) -> float:
    """The largest channel standard deviation of (N, >= 3) colours, 0-255 levels."""
    c = np.asarray(colours, dtype=np.float64).reshape(-1, np.shape(colours)[-1])[:, :3]
    return float(c.std(axis=0).max()) if len(c) else 0.0


def surface_appearance(mesh) -> str:
    """What a ``trimesh.Trimesh``'s surface shows: "textured" (a texture image, or vertex or
    face colours, whose colours vary), "uniform" (one colour: a flat texture, a material's
    colour alone, or equal colours) or "none" (no texture and no colours). A texture image
    is judged as a whole (a :data:`_TEXTURE_PREVIEW_PX` copy): colours it holds outside the
    mesh's UVs count too, so a textured mesh is never taken for one colour."""
    visual = getattr(mesh, "visual", None)
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        material = getattr(visual, "material", None)
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is None:
            return "uniform"
        n = _TEXTURE_PREVIEW_PX
        preview = np.asarray(image.convert("RGB").resize((n, n)))
        return "textured" if _spread(preview) > UNIFORM_COLOUR_STD else "uniform"
    if kind in ("vertex", "face"):
        colours = visual.vertex_colors if kind == "vertex" else visual.face_colors
        return "textured" if _spread(colours) > UNIFORM_COLOUR_STD else "uniform"
    return "none"


@dataclass
class AppearanceResult:
    """One candidate's comparison: scores (S,) the colour score per rotation (the check's
    rotations' order), pose_scores (S,) what chose the pose (the texture features' similarity,
    else ``scores``), best (index), R, t (the chosen pose), ambiguous (indices of the rotations
    whose pose score is within the margin of the best, the best excluded)."""

    scores: np.ndarray
    pose_scores: np.ndarray
    best: int
    R: np.ndarray
    t: np.ndarray
    ambiguous: tuple[int, ...]

    @property
    def score(self) -> float:
        """How much the object looks like the mesh at all: the best colour score of its poses."""
        return float(self.scores.max()) if len(self.scores) else 0.0


def crop_transform(box: np.ndarray, side_px: int, margin: float) -> tuple[np.ndarray, float]:
    """The square crop around a projected box [u_min, v_min, u_max, v_max] px: (2,) its
    top-left corner (u0, v0) and the scale s (crop px per image px); a crop pixel x shows the
    image at u0 + x / s."""
    lo, hi = np.asarray(box[:2], dtype=np.float64), np.asarray(box[2:], dtype=np.float64)
    side = max(float(np.max(hi - lo)) * (1.0 + 2.0 * margin), 4.0)
    centre = (lo + hi) / 2.0
    return centre - side / 2.0, side_px / side


def chromaticity_histogram(rgb: np.ndarray, bins: int) -> np.ndarray:
    """(bins, bins) normalized histogram of r = R / (R + G + B), g = G / (R + G + B) of (N, 3)
    colours (sums to 1; all zero for no pixel)."""
    c = np.asarray(rgb, dtype=np.float64)
    total = c.sum(axis=1) + 1e-6
    h, _, _ = np.histogram2d(c[:, 0] / total, c[:, 1] / total, bins=bins, range=((0, 1), (0, 1)))
    n = h.sum()
    return h / n if n > 0 else h


def appearance_similarity(image: np.ndarray, rendered: np.ndarray, mask: np.ndarray, bins: int,
                          texture: bool = True) -> float:
    """Score in [0, 1] of (H, W, 3) ``image`` against (H, W, 3) ``rendered`` inside (H, W)
    ``mask``: the mean of the colour channels' normalized cross-correlation (negative: 0) and
    the chromaticity histograms' intersection; ``texture`` False (a mesh of one colour, whose
    render has no texture to correlate): the intersection alone."""
    a = np.asarray(image, dtype=np.float64)[mask]
    b = np.asarray(rendered, dtype=np.float64)[mask]
    inter = float(np.minimum(chromaticity_histogram(a, bins), chromaticity_histogram(b, bins)).sum())
    if not texture:
        return inter
    a0, b0 = a - a.mean(axis=0), b - b.mean(axis=0)
    den = np.sqrt((a0 ** 2).sum() * (b0 ** 2).sum())
    ncc = float((a0 * b0).sum() / den) if den > 1e-9 else 0.0
    return 0.5 * max(ncc, 0.0) + 0.5 * inter


def feature_similarity(image_features: np.ndarray, render_features: np.ndarray, mask: np.ndarray,
                       min_cells: int = 4) -> float:
    """Mean cosine, in [-1, 1], of (C, h, w) ``image_features`` and ``render_features`` over the
    cells whose whole area lies inside the (H, W) silhouette ``mask`` (eroded by a pixel: a
    render's edge cells see its black background); 0 for fewer than ``min_cells`` cells."""
    h, w = np.shape(image_features)[1:]
    inner = cv2.erode(np.asarray(mask, np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    cells = cv2.resize(inner, (w, h), interpolation=cv2.INTER_AREA) > 0.99
    if cells.sum() < min_cells:
        return 0.0
    a = np.asarray(image_features, dtype=np.float64)[:, cells]
    b = np.asarray(render_features, dtype=np.float64)[:, cells]
    den = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0)
    return float(np.mean(np.where(den > 1e-12, (a * b).sum(axis=0) / np.maximum(den, 1e-12), 0.0)))


class AppearanceCheck:
    """Render-and-compare of one mesh's candidate poses.

    Args:
        mesh: the textured ``trimesh.Trimesh``, metres, mesh frame.
        symmetries: (S, 3, 3) mesh-frame rotations about ``center`` that leave the detector
            unable to tell the poses apart (identity first), e.g.
            :func:`dope_hope.symmetry.cuboid.cuboid_rotations`.
        center: (3,) the point they turn about (the cuboid centre), metres.
        settings: :class:`AppearanceSettings`.
        up: (3,) the mesh's up axis, about which the turns of ``settings.spin_step_deg`` are
            compared too (None: the symmetries alone).
        surface: :func:`surface_appearance` of ``mesh`` where the caller has it (None: found here).
        features: the network's first layers, (N, H, W, 3) uint8 -> (N, C, h, w)
            (:meth:`~dope_hope.inference.backends.TorchBackend.texture_features`); they choose
            the pose where ``settings.texture_features`` and the surface is textured (None: the
            colour score chooses).
        upside_down: compare the turns upside down too (:func:`candidate_rotations`).

    Attributes: surface (:func:`surface_appearance`: "textured" or "uniform"; "none" is
    refused with a ConfigError); rotations (S', 3, 3): those compared
    (:func:`candidate_rotations`), the ``symmetries`` first (a uniform surface: the identity
    alone, no pose told from another); n_symmetries: how many of them the symmetries are.
    """

    def __init__(self, mesh, symmetries: np.ndarray, center: np.ndarray,
                 settings: AppearanceSettings | None = None, up: np.ndarray | None = None,
                 surface: str | None = None, features: Callable[[np.ndarray], np.ndarray] | None = None,
                 upside_down: bool = True):
        from dope_hope.render.textured import TexturedRenderer  # noqa: PLC0415 (OpenGL (pyrender's EGL) only when a candidate is rendered)

        self.settings = settings or AppearanceSettings()
        self.surface = surface or surface_appearance(mesh)
        if self.surface == "none":
            raise ConfigError("the appearance check needs a mesh with a texture or colours; this one has neither")
        symmetries = np.asarray(symmetries, dtype=np.float64).reshape(-1, 3, 3)
        if self.surface == "uniform":
            symmetries, up = symmetries[:1], None
        self.n_symmetries = len(symmetries)
        self.features = features if self.settings.texture_features and self.surface == "textured" else None
        self.rotations = candidate_rotations(symmetries, up, self.settings.spin_step_deg, upside_down)
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
        n = self.settings.crop_px
        self._renderer = TexturedRenderer(mesh, n, n)

    def turned_pose(self, R: np.ndarray, t: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose ``R S`` for a mesh-frame rotation S (3, 3) about the centre."""
        RS = np.asarray(R, dtype=np.float64) @ np.asarray(S, dtype=np.float64)
        return RS, np.asarray(t, dtype=np.float64) + R @ self.center - RS @ self.center

    def compare(self, rgb: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                turns: bool = True, rotations: np.ndarray | None = None) -> AppearanceResult:
        """Score every pose ``R S`` of the candidate (R (3, 3), t (3,) m; S of ``rotations``, or
        of its first ``n_symmetries`` without ``turns``; or of the (S, 3, 3) ``rotations``
        given, identity first) in the (H, W, 3) uint8 image with intrinsics K (3, 3)."""
        s = self.settings
        K = np.asarray(K, dtype=np.float64)
        compared = self.rotations if rotations is None else np.asarray(rotations, dtype=np.float64)
        count = len(compared) if turns or rotations is not None else self.n_symmetries
        scores = np.zeros(count)
        uv = project_points(self.hull, K, R, t)
        if float(np.asarray(t)[2]) <= 0 or not np.all(np.isfinite(uv)):
            return AppearanceResult(scores, scores, 0, np.asarray(R, float), np.asarray(t, float), ())
        box = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
        (u0, v0), scale = crop_transform(box, s.crop_px, s.margin)
        M = np.array([[scale, 0.0, -u0 * scale], [0.0, scale, -v0 * scale]])
        crop = cv2.warpAffine(np.ascontiguousarray(rgb[..., :3]), M, (s.crop_px, s.crop_px), flags=cv2.INTER_AREA
                              if scale < 1 else cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inside = cv2.warpAffine(np.ones(rgb.shape[:2], np.uint8), M, (s.crop_px, s.crop_px),
                                flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
        K_crop = np.array([[scale, 0.0, -u0 * scale], [0.0, scale, -v0 * scale], [0.0, 0.0, 1.0]]) @ K
        poses = [self.turned_pose(R, t, S) for S in compared[:count]]
        renders = []
        for k, (Rk, tk) in enumerate(poses):
            rendered, mask = self._renderer.render(Rk, tk, K_crop)
            mask &= inside
            renders.append((rendered, mask))
            if mask.sum() >= s.min_pixels:
                scores[k] = appearance_similarity(crop, rendered, mask, s.hist_bins, self.surface == "textured")
        pose_scores = scores
        if self.features is not None and count > 1:
            f = self.features(np.stack([crop] + [rendered for rendered, _ in renders]))
            pose_scores = np.array([feature_similarity(f[0], f[k + 1], mask) if mask.sum() >= s.min_pixels else -1.0
                                    for k, (_, mask) in enumerate(renders)])
        best = int(np.argmax(pose_scores))
        ambiguous = tuple(int(k) for k in np.flatnonzero(pose_scores >= pose_scores[best] - s.ambiguity_margin)
                          if k != best)
        return AppearanceResult(scores, pose_scores, best, poses[best][0], poses[best][1], ambiguous)

    def close(self) -> None:
        """Free the renderer's GL context."""
        self._renderer.close()
