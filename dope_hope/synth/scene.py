"""Scene sampling: camera, target instances, distractors, occluders and lights of one frame.

Pure numpy (no OpenGL): a :class:`SceneSpec` says everything the renderer needs. Poses are
in the OpenCV camera frame (x right, y down, z forward), ``x_c = R x + t``, metres.

Every part draws from its own random stream (:func:`frame_streams`), so switching an option
(e.g. forcing an occluder, adding depth noise) leaves the rest of the frame unchanged.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.config import SectionSettings
from dope_hope.synth.camera import sample_intrinsics
from dope_hope.synth.hard_negatives import TargetLook, hard_negative_geometry, hard_negative_material
from dope_hope.synth.primitives import dims_for_radius, make_primitive, sample_dims
from dope_hope.synth.textures import procedural_image, random_color

#: Names of the per-frame random streams, in spawn order (never reorder: it changes datasets;
#: a new stream goes at the end). "object": the frame's procedural target (synth/objects.py).
STREAM_NAMES = ("camera", "targets", "distractors", "lights", "background", "post",
                "occluders", "depth_noise", "object", "hard_negatives")


def frame_streams(seed: int, index: int) -> dict[str, np.random.Generator]:
    """Independent generators for frame ``index`` of a dataset with ``seed``.

    Derived from ``np.random.SeedSequence([seed, index])``: the same (seed, index) gives the
    same frame on any machine, in any worker, in any order.
    """
    children = np.random.SeedSequence([int(seed), int(index)]).spawn(len(STREAM_NAMES))
    return {name: np.random.default_rng(s) for name, s in zip(STREAM_NAMES, children)}


@dataclass
class MaterialSpec:
    """Surface of one object.

    Attributes:
        base_color: (4,) RGBA factor in [0, 1].
        metallic, roughness: PBR factors.
        texture: (h, w, 3) uint8 procedural texture, or None.
        keep_texture: mesh distractors / the target: use the mesh's own texture (tinted).
    """

    base_color: np.ndarray
    metallic: float
    roughness: float
    texture: np.ndarray | None = None
    keep_texture: bool = False


@dataclass
class ObjectSpec:
    """One object in the scene.

    Attributes:
        role: "target", "distractor" or "hard_negative" (a distractor that looks like the
            target: :mod:`dope_hope.synth.hard_negatives`). Only targets are annotated.
        seg_id: its id in the segmentation image (targets 1..k, distractors and hard
            negatives base + j).
        R: (3, 3), t: (3,) pose of the model frame in the camera frame (metres).
        radius: bounding-sphere radius about the box centre, metres.
        center: (3,) bounding-sphere centre in the camera frame, metres.
        source: "target", "primitive" or "mesh".
        mesh_index: index into the distractor mesh list (source "mesh").
        geometry: the primitive's trimesh (source "primitive").
        material: its material.
        occluder_of: for occluders, the seg id of the target it was placed in front of.
        target_index: for targets, which of the generator's target objects it is (0 with
            one target object).
    """

    role: str
    seg_id: int
    R: np.ndarray
    t: np.ndarray
    radius: float
    center: np.ndarray
    source: str
    material: MaterialSpec
    mesh_index: int | None = None
    geometry: Any = None
    occluder_of: int | None = None
    target_index: int = 0


@dataclass
class LightSpec:
    """One light. Directions are unit vectors of travel, camera frame; colour RGB in [0, 1]."""

    kind: str
    color: np.ndarray
    intensity: float
    position: np.ndarray
    direction: np.ndarray
    inner_cone: float = 0.0
    outer_cone: float = 0.0


@dataclass
class SceneSpec:
    """Everything that defines one frame's geometry and lighting."""

    width: int
    height: int
    K: np.ndarray
    znear: float
    zfar: float
    objects: list[ObjectSpec] = field(default_factory=list)
    lights: list[LightSpec] = field(default_factory=list)
    ambient: float = 0.2
    target_material: MaterialSpec | None = None

    @property
    def targets(self) -> list[ObjectSpec]:
        return [o for o in self.objects if o.role == "target"]


@dataclass
class ShapeInfo:
    """Model-frame bounding sphere of a mesh: centre (3,) and radius, metres."""

    center: np.ndarray
    radius: float


def _weighted_choice(rng: np.random.Generator, weights: dict[str, float]) -> str:
    keys = [k for k, v in weights.items() if float(v) > 0]
    p = np.array([float(weights[k]) for k in keys])
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def _backproject(K: np.ndarray, u: float, v: float, z: float) -> np.ndarray:
    return z * np.linalg.solve(K, np.array([u, v, 1.0]))


def _free(center: np.ndarray, radius: float, placed: list[ObjectSpec], factor: float) -> bool:
    return all(np.linalg.norm(center - o.center) >= factor * (radius + o.radius) for o in placed)


def _pixel_inside(rng: np.random.Generator, extent: int, margin: float) -> float:
    """Uniform coordinate in [margin, extent - 1 - margin] (the centre if that is empty)."""
    lo, hi = margin, extent - 1 - margin
    return float(rng.uniform(lo, hi)) if hi > lo else (extent - 1) / 2.0


def _target_center_pixel(rng: np.random.Generator, W: int, H: int, r_px: float,
                         cfg: SectionSettings) -> tuple[float, float]:
    if rng.random() < cfg.truncation_prob:
        border = int(rng.integers(0, 4))            # 0 left, 1 right, 2 top, 3 bottom
        off = rng.uniform(*cfg.truncation_offset) * r_px
        along = _pixel_inside(rng, H if border < 2 else W, 0.0)
        if border == 0:
            return -0.5 - off, along
        if border == 1:
            return W - 0.5 + off, along
        if border == 2:
            return along, -0.5 - off
        return along, H - 0.5 + off
    m = cfg.inside_margin * r_px
    return _pixel_inside(rng, W, m), _pixel_inside(rng, H, m)


def sample_targets(rng: np.random.Generator, K: np.ndarray, W: int, H: int,
                   shapes: ShapeInfo | Sequence[ShapeInfo], cfg: SectionSettings) -> list[ObjectSpec]:
    """Target instances: uniform random rotation, centre depth in ``distance_m``, no overlap.

    ``shapes``: the bounding sphere of each target object (one, or one per object). With
    several objects the frame's ``count`` instances take their objects from a random
    permutation of them, cycled (distinct objects while the count allows; which objects a
    frame shows is random, and a count of 0 is a negative frame); ``target_index`` records it.
    With one object no extra number is drawn (its frames are the one-object generator's).
    """
    shapes = [shapes] if isinstance(shapes, ShapeInfo) else list(shapes)
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    order = rng.permutation(len(shapes)) if len(shapes) > 1 else np.zeros(1, int)
    placed: list[ObjectSpec] = []
    for i in range(n):
        k = int(order[i % len(order)])
        shape = shapes[k]
        for _try in range(int(cfg.max_tries)):
            R = Rotation.random(random_state=rng).as_matrix()
            z = rng.uniform(*cfg.distance_m)
            r_px = K[0, 0] * shape.radius / z
            u, v = _target_center_pixel(rng, W, H, r_px, cfg)
            c = _backproject(K, u, v, z)
            if _free(c, shape.radius, placed, cfg.separation_factor):
                t = c - R @ shape.center
                placed.append(ObjectSpec(role="target", seg_id=len(placed) + 1, R=R, t=t,
                                         radius=shape.radius, center=c, source="target",
                                         material=MaterialSpec(np.ones(4), 0.0, 0.5, keep_texture=True),
                                         target_index=k))
                break
    return placed


def sample_material(rng: np.random.Generator, cfg: SectionSettings) -> MaterialSpec:
    """Random colour, metallic, roughness and (with ``texture_prob``) a procedural texture."""
    color = np.append(random_color(rng, value=(0.15, 1.0)), 1.0)
    metallic = float(rng.uniform(*cfg.metallic))
    roughness = float(rng.uniform(*cfg.roughness))
    texture = None
    if rng.random() < cfg.texture_prob:
        px = int(cfg.texture_px)
        texture = procedural_image(rng, px, px)
        color = np.array([1.0, 1.0, 1.0, 1.0])
    return MaterialSpec(color, metallic, roughness, texture)


def _distractor_shape(rng: np.random.Generator, cfg: SectionSettings, n_meshes: int,
                      mesh_info: Callable[[int], ShapeInfo] | None,
                      radius: float | None = None) -> dict[str, Any]:
    """Geometry + material of one distractor (mesh from the library or a primitive)."""
    use_mesh = n_meshes > 0 and mesh_info is not None and radius is None and \
        rng.random() < cfg.mesh_prob
    if use_mesh:
        idx = int(rng.integers(0, n_meshes))
        info = mesh_info(idx)
        if rng.random() < cfg.keep_texture_prob:
            tint = np.append(rng.uniform(*cfg.tint, size=3), 1.0)
            material = MaterialSpec(tint, float(rng.uniform(0.0, 0.3)),
                                    float(rng.uniform(*cfg.roughness)), keep_texture=True)
        else:
            material = sample_material(rng, cfg)
        return dict(source="mesh", mesh_index=idx, geometry=None, model_center=info.center,
                    radius=info.radius, material=material)
    kind = _weighted_choice(rng, cfg.primitives.to_dict())
    dims = dims_for_radius(kind, radius, rng) if radius is not None else \
        sample_dims(rng, kind, tuple(cfg.size_m))
    mesh = make_primitive(kind, dims, tile_m=float(rng.uniform(*cfg.texture_tile_m)))
    r = float(np.linalg.norm(mesh.vertices, axis=1).max())
    return dict(source="primitive", mesh_index=None, geometry=mesh, model_center=np.zeros(3),
                radius=r, material=sample_material(rng, cfg))


def sample_distractors(rng: np.random.Generator, K: np.ndarray, W: int, H: int,
                       placed: list[ObjectSpec], cfg: SectionSettings, seg_base: int,
                       n_meshes: int = 0,
                       mesh_info: Callable[[int], ShapeInfo] | None = None) -> list[ObjectSpec]:
    """Distractors anywhere in the (slightly enlarged) view, not intersecting placed objects."""
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    out: list[ObjectSpec] = []
    mx, my = cfg.outside_margin * W, cfg.outside_margin * H
    for _ in range(n):
        shape = _distractor_shape(rng, cfg, n_meshes, mesh_info)
        R = Rotation.random(random_state=rng).as_matrix()
        for _try in range(20):
            z = rng.uniform(*cfg.distance_m)
            c = _backproject(K, rng.uniform(-mx, W - 1 + mx), rng.uniform(-my, H - 1 + my), z)
            if _free(c, shape["radius"], placed + out, 1.0):
                out.append(ObjectSpec(role="distractor", seg_id=seg_base + len(out) + 1, R=R,
                                      t=c - R @ shape["model_center"], radius=shape["radius"],
                                      center=c, source=shape["source"], material=shape["material"],
                                      mesh_index=shape["mesh_index"], geometry=shape["geometry"]))
                break
    return out


def sample_occluders(rng: np.random.Generator, K: np.ndarray, targets: list[ObjectSpec],
                     others: list[ObjectSpec], cfg: SectionSettings, znear: float,
                     first_seg_id: int, force: int | None = None) -> list[ObjectSpec]:
    """Primitives placed between the camera and target instances (partial occlusion).

    Each target gets one with probability ``occluder_prob`` (placed clear of ``others``, the
    distractors); ``force`` (a target's list index)
    always gets one with a small offset (0.3 of ``occluder_offset``'s lower end), i.e. a heavy
    occlusion — used by tests and demos.
    """
    out: list[ObjectSpec] = []
    for i, tgt in enumerate(targets):
        draw = rng.random()
        forced = force is not None and i == force
        if not forced and draw >= cfg.occluder_prob:
            continue
        shape = _distractor_shape(rng, cfg, 0, None,
                                  radius=tgt.radius * rng.uniform(*cfg.occluder_radius))
        R = Rotation.random(random_state=rng).as_matrix()
        c_t = tgt.center
        uv_t = (K @ c_t)[:2] / c_t[2]
        r_px = K[0, 0] * tgt.radius / c_t[2]
        for _try in range(20):
            free_far = c_t[2] - tgt.radius - shape["radius"]   # occluder centre must be closer
            free_near = znear + 0.05 + shape["radius"]
            if free_far <= free_near:
                break
            z = free_near + rng.uniform(*cfg.occluder_depth) * (free_far - free_near)
            off = (0.3 * cfg.occluder_offset[0] if forced else rng.uniform(*cfg.occluder_offset))
            ang = rng.uniform(0, 2 * np.pi)
            uv = uv_t + off * r_px * np.array([np.cos(ang), np.sin(ang)])
            c = _backproject(K, uv[0], uv[1], z)
            # a forced occluder may touch distractors; a random one avoids them too
            if _free(c, shape["radius"], targets + out + ([] if forced else others), 1.0):
                out.append(ObjectSpec(role="distractor", seg_id=first_seg_id + len(out), R=R,
                                      t=c - R @ shape["model_center"], radius=shape["radius"],
                                      center=c, source="primitive", material=shape["material"],
                                      geometry=shape["geometry"], occluder_of=tgt.seg_id))
                break
    return out


def sample_hard_negatives(rng: np.random.Generator, K: np.ndarray, W: int, H: int,
                          placed: list[ObjectSpec], look: TargetLook | Sequence[TargetLook],
                          cfg: SectionSettings, target_cfg: dict[str, Any],
                          first_seg_id: int) -> list[ObjectSpec]:
    """Look-alikes of the target (:mod:`dope_hope.synth.hard_negatives`), placed as the targets
    are (``target_cfg``: depth band, margins, truncation, separation) clear of ``placed``.
    With several target objects (``look`` one per object) each look-alike imitates a random one.

    Role "hard_negative", seg ids ``first_seg_id``, ``first_seg_id + 1``, ...; never annotated.
    """
    looks = [look] if isinstance(look, TargetLook) else list(look)
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    out: list[ObjectSpec] = []
    for _ in range(n):
        one = looks[int(rng.integers(0, len(looks)))] if len(looks) > 1 else looks[0]
        geometry = hard_negative_geometry(rng, one, cfg)
        color, texture = hard_negative_material(rng, one, cfg)
        material = MaterialSpec(color, 0.0, float(rng.uniform(*target_cfg.roughness)), texture)
        radius = float(np.linalg.norm(geometry.vertices, axis=1).max())
        R = Rotation.random(random_state=rng).as_matrix()
        for _try in range(int(target_cfg.max_tries)):
            z = rng.uniform(*target_cfg.distance_m)
            u, v = _target_center_pixel(rng, W, H, K[0, 0] * radius / z, target_cfg)
            c = _backproject(K, u, v, z)
            if _free(c, radius, placed + out, target_cfg.separation_factor):
                out.append(ObjectSpec(role="hard_negative", seg_id=first_seg_id + len(out), R=R, t=c,
                                      radius=radius, center=c, source="primitive", material=material,
                                      geometry=geometry))
                break
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _direction_in_cone(rng: np.random.Generator, axis: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """Unit vector uniformly distributed (by solid angle) within ``max_angle_deg`` of ``axis``."""
    cos_max = np.cos(np.radians(max_angle_deg))
    cz = rng.uniform(cos_max, 1.0)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    sz = np.sqrt(max(0.0, 1.0 - cz * cz))
    local = np.array([sz * np.cos(phi), sz * np.sin(phi), cz])
    a = _unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _unit(np.cross(helper, a))
    y = np.cross(a, x)
    return local[0] * x + local[1] * y + local[2] * a


def sample_lights(rng: np.random.Generator, targets: list[ObjectSpec],
                  cfg: SectionSettings) -> tuple[list[LightSpec], float]:
    """Lights of random kind, colour, intensity, position and direction; plus the ambient level."""
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    lights = []
    pos_cfg = cfg.position_m
    for _ in range(n):
        kind = _weighted_choice(rng, cfg.types.to_dict())
        color = random_color(rng, saturation=tuple(cfg.saturation), value=(1.0, 1.0))
        intensity = float(rng.uniform(*cfg.intensity.to_dict()[kind]))
        position = np.array([rng.uniform(*pos_cfg.x), rng.uniform(*pos_cfg.y),
                             rng.uniform(*pos_cfg.z)])
        if kind == "directional":
            direction = _direction_in_cone(rng, np.array([0.0, 0.0, 1.0]), cfg.max_angle_deg)
        else:
            aim = targets[int(rng.integers(0, len(targets)))].center if targets else np.array([0, 0, 1.0])
            direction = _unit(aim + rng.normal(0.0, 0.05, 3) - position)
        outer = np.radians(rng.uniform(*cfg.spot_outer_deg))
        inner = outer * rng.uniform(*cfg.spot_inner_ratio)
        lights.append(LightSpec(kind, color, intensity, position, direction, inner, outer))
    return lights, float(rng.uniform(*cfg.ambient))


def sample_scene(streams: dict[str, np.random.Generator], size: tuple[int, int],
                 cfg: SectionSettings, target_shape: ShapeInfo | Sequence[ShapeInfo],
                 n_distractor_meshes: int = 0,
                 distractor_info: Callable[[int], ShapeInfo] | None = None,
                 force_occluder: int | None = None,
                 target_look: TargetLook | Sequence[TargetLook] | None = None) -> SceneSpec:
    """The complete random scene of one frame (see module docstring for the streams).

    Args:
        streams: from :func:`frame_streams`.
        size: (W, H) pixels.
        cfg: the synth config.
        target_shape: bounding sphere of the target mesh (model frame), or one per target
            object (:func:`sample_targets`).
        n_distractor_meshes, distractor_info: the distractor mesh library (size, bounds of i).
        force_occluder: index of a target instance that must get an occluder in front.
        target_look: the target's size, shape class and colours, for the hard negatives
            (none without it); one per target object with several.
    """
    W, H = size
    K = sample_intrinsics(streams["camera"], size, cfg.camera)
    targets = sample_targets(streams["targets"], K, W, H, target_shape, cfg.target)
    t_rng = streams["targets"]
    target_material = MaterialSpec(np.append(np.full(3, t_rng.uniform(*cfg.target.brightness)), 1.0),
                                   0.0, float(t_rng.uniform(*cfg.target.roughness)), keep_texture=True)
    for t in targets:
        t.material = target_material
    base = int(cfg.output.seg_distractor_base)
    distractors = sample_distractors(streams["distractors"], K, W, H, list(targets),
                                     cfg.distractors, base, n_distractor_meshes, distractor_info)
    occluders = sample_occluders(streams["occluders"], K, targets, distractors, cfg.distractors,
                                 cfg.camera.znear, base + len(distractors) + 1, force_occluder)
    lookalikes = [] if target_look is None else sample_hard_negatives(
        streams["hard_negatives"], K, W, H, targets + distractors + occluders, target_look,
        cfg.hard_negatives, cfg.target, base + len(distractors) + len(occluders) + 1)
    lights, ambient = sample_lights(streams["lights"], targets, cfg.lights)
    return SceneSpec(width=W, height=H, K=K, znear=float(cfg.camera.znear),
                     zfar=float(cfg.camera.zfar),
                     objects=targets + distractors + occluders + lookalikes,
                     lights=lights, ambient=ambient, target_material=target_material)
