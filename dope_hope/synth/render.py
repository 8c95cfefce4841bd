"""Offscreen rendering of a :class:`SceneSpec` with pyrender (headless EGL).

Passes per frame:

1. colour (RGBA, 4x MSAA, shadows optional): objects over a transparent background; the
   alpha channel is the anti-aliased coverage used for compositing.
2. segmentation (no MSAA, flat ids): the instance-id image and the depth image, both sampled
   at pixel centres, so that depth and ids agree pixel for pixel.
3. one segmentation pass per target instance with only that instance drawn, on a canvas
   around its projected cuboid (inside or outside the image): its unoccluded, untruncated
   pixel count (the visibility denominator) and its depth when alone.

Camera: OpenCV K; pyrender's window coordinates put pixel centres at half-integers, so the
GL principal point is (cx + 0.5, cy + 0.5). Object poses are converted to the OpenGL camera
frame (y up, z backwards) with ``diag(1, -1, -1)``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.render.gl import CV_TO_GL, close_offscreen, gl_camera, import_pyrender, pose_gl
from dope_hope.synth.scene import LightSpec, ObjectSpec, SceneSpec

pyrender = import_pyrender()

#: Largest alone-render canvas side, as a multiple of the image side (bounds the cost).
MAX_CANVAS_FACTOR = 4


@dataclass
class RenderOutput:
    """Arrays of one rendered frame (before compositing).

    Attributes:
        color: (H, W, 3) uint8 premultiplied object colours (black where no object).
        alpha: (H, W) float32 coverage in [0, 1].
        depth: (H, W) float32 metres, 0 where no object (pixel-centre samples).
        seg: (H, W) uint8 instance ids (0 background).
        px_all: seg id -> pixels of that target instance rendered alone, whole object.
        alone_depth: seg id -> (H, W) float32 depth of that target instance alone (in image).
    """

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    seg: np.ndarray
    px_all: dict[int, int] = field(default_factory=dict)
    alone_depth: dict[int, np.ndarray] = field(default_factory=dict)


def _light_pose(light: LightSpec) -> np.ndarray:
    """Node pose whose -z axis is the light's travel direction (OpenGL frame)."""
    d = CV_TO_GL @ light.direction
    z = -d / np.linalg.norm(d)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = CV_TO_GL @ light.position
    return T


def _make_light(light: LightSpec) -> pyrender.Light:
    if light.kind == "directional":
        return pyrender.DirectionalLight(color=light.color, intensity=light.intensity)
    if light.kind == "point":
        return pyrender.PointLight(color=light.color, intensity=light.intensity)
    if light.kind == "spot":
        return pyrender.SpotLight(color=light.color, intensity=light.intensity,
                                  innerConeAngle=light.inner_cone, outerConeAngle=light.outer_cone)
    raise ValueError(f"unknown light kind {light.kind!r}")


def alone_canvas(obj_keypoints_uv: np.ndarray, width: int, height: int) -> tuple[int, int, int, int]:
    """Canvas (x0, y0, W', H') in image pixel coordinates that holds the whole object.

    The box of the projected cuboid (9, 2) px plus a 2-pixel margin; its size is capped at
    ``MAX_CANVAS_FACTOR`` times the image size (then centred on the image-facing part).
    """
    lo = np.floor(np.nanmin(obj_keypoints_uv, axis=0)).astype(int) - 2
    hi = np.ceil(np.nanmax(obj_keypoints_uv, axis=0)).astype(int) + 2
    out = []
    for axis, extent in enumerate((width, height)):
        a, b = int(lo[axis]), int(hi[axis])
        cap = MAX_CANVAS_FACTOR * extent
        if b - a + 1 > cap:  # keep the part nearest to the image
            mid = min(max((a + b) // 2, 0), extent - 1)
            a, b = mid - cap // 2, mid - cap // 2 + cap - 1
        out.append((a, b - a + 1))
    return out[0][0], out[1][0], out[0][1], out[1][1]


class SceneRenderer:
    """Owns one OffscreenRenderer (one OpenGL context: one per process).

    Args:
        width, height: default viewport (changed per call as needed).
        shadows: shadow maps for directional and spot lights.
    """

    def __init__(self, width: int, height: int, shadows: bool = True):
        self._r = pyrender.OffscreenRenderer(width, height)
        self.shadows = shadows

    def close(self) -> None:
        """Free this renderer's GL objects and context (:func:`~dope_hope.render.gl.close_offscreen`)."""
        if self._r is None:
            return
        r, self._r = self._r, None
        close_offscreen(r)

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _viewport(self, w: int, h: int) -> None:
        self._r.viewport_width, self._r.viewport_height = int(w), int(h)

    def render(self, spec: SceneSpec, mesh_for: Callable[[ObjectSpec], pyrender.Mesh],
               cuboid_for_target: tuple[np.ndarray, np.ndarray]
               | Callable[[ObjectSpec], tuple[np.ndarray, np.ndarray]] | None = None,
               with_alone_depth: bool = False) -> RenderOutput:
        """Render all passes of a scene.

        Args:
            spec: the scene.
            mesh_for: the pyrender mesh of an object.
            cuboid_for_target: (size (3,), center (3,)) of the target's cuboid, or a function
                giving it for a target instance (several target objects), to size the
                alone-render canvas (default: the bounding sphere's box).
            with_alone_depth: also return each target's alone depth (tests, diagnostics).
        """
        W, H = spec.width, spec.height
        scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.full(3, spec.ambient))
        scene.add(gl_camera(spec.K, spec.znear, spec.zfar), pose=np.eye(4))
        nodes = []
        for obj in spec.objects:
            nodes.append(scene.add(mesh_for(obj), pose=pose_gl(obj.R, obj.t)))
        for light in spec.lights:
            scene.add(_make_light(light), pose=_light_pose(light))

        flags = pyrender.RenderFlags.RGBA
        if self.shadows:
            flags |= pyrender.RenderFlags.SHADOWS_DIRECTIONAL | pyrender.RenderFlags.SHADOWS_SPOT
        self._viewport(W, H)
        rgba, _ = self._r.render(scene, flags=flags)
        rgba = np.asarray(rgba)
        seg_map = {n: np.full(3, o.seg_id) for n, o in zip(nodes, spec.objects)}
        seg_rgb, depth = self._r.render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
        seg = np.ascontiguousarray(np.asarray(seg_rgb)[:, :, 0])

        out = RenderOutput(color=np.ascontiguousarray(rgba[:, :, :3]),
                           alpha=rgba[:, :, 3].astype(np.float32) / 255.0,
                           depth=np.ascontiguousarray(depth, dtype=np.float32), seg=seg)
        for node, obj in zip(nodes, spec.objects):
            if obj.role != "target":
                continue
            if cuboid_for_target is not None:
                size, center = cuboid_for_target(obj) if callable(cuboid_for_target) else cuboid_for_target
                kp = cuboid_keypoints(size, center)
            else:
                kp = cuboid_keypoints(np.full(3, 2 * obj.radius), np.linalg.solve(obj.R, obj.center - obj.t))
            uv = project_points(kp, spec.K, obj.R, obj.t)
            x0, y0, cw, ch = alone_canvas(uv, W, H)
            scene.main_camera_node.camera = gl_camera(spec.K, spec.znear, spec.zfar, -x0, -y0)
            self._viewport(cw, ch)
            mask_rgb, d_alone = self._r.render(scene, flags=pyrender.RenderFlags.SEG,
                                               seg_node_map={node: np.full(3, 255)})
            full = np.asarray(mask_rgb)[:, :, 0] > 0
            out.px_all[obj.seg_id] = int(full.sum())
            if with_alone_depth:  # paste the canvas's overlap with the image
                d_img = np.zeros((H, W), np.float32)
                u0, u1 = max(x0, 0), min(x0 + cw, W)
                v0, v1 = max(y0, 0), min(y0 + ch, H)
                if u1 > u0 and v1 > v0:
                    d_img[v0:v1, u0:u1] = np.asarray(d_alone)[v0 - y0:v1 - y0, u0 - x0:u1 - x0]
                out.alone_depth[obj.seg_id] = d_img
        scene.main_camera_node.camera = gl_camera(spec.K, spec.znear, spec.zfar)
        self._viewport(W, H)
        return out
