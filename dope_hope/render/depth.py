"""Depth images of a mesh in a pose (pyrender, headless EGL): what VSD compares against."""
from __future__ import annotations

from typing import Any

import numpy as np


# --------------------------------------------------------------------------- VSD
class DepthRenderer:
    """Depth images of meshes in given poses, rendered with pyrender (headless EGL).

    Keeps one ``OffscreenRenderer`` per image size and one scene per mesh, so repeated
    calls (VSD over a whole dataset) only move the object and the camera.
    """

    def __init__(self, znear: float = 0.01, zfar: float = 100.0):
        from dope_hope.render.gl import import_pyrender

        self._pr = import_pyrender()
        self.znear, self.zfar = znear, zfar
        self._renderers: dict[tuple[int, int], Any] = {}
        self._scenes: dict[int, tuple[Any, Any, Any, Any]] = {}  # id(mesh) -> (mesh, scene, node, cam)
        self._rays: dict[tuple, np.ndarray] = {}

    def _scene(self, mesh):
        entry = self._scenes.get(id(mesh))
        if entry is None or entry[0] is not mesh:
            pr = self._pr
            scene = pr.Scene(bg_color=(0, 0, 0, 0), ambient_light=(1.0, 1.0, 1.0))
            node = scene.add(pr.Mesh.from_trimesh(mesh, smooth=False))
            cam = pr.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=self.znear, zfar=self.zfar)
            scene.add(cam, pose=np.eye(4))
            entry = self._scenes[id(mesh)] = (mesh, scene, node, cam)
        return entry

    def render_depth(self, mesh, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                     width: int, height: int) -> np.ndarray:
        """(height, width) float32 depth (z, metres) of ``mesh`` (metres) in pose (R, t); 0 = none."""
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        _, scene, node, cam = self._scene(mesh)
        # OpenCV camera -> OpenGL camera (y up, looking down -z): flip y and z.
        pose = np.eye(4)
        pose[:3, :3] = R
        pose[:3, 3] = t
        scene.set_pose(node, np.diag([1.0, -1.0, -1.0, 1.0]) @ pose)
        # pyrender puts pixel centres at half-integers; ours are at integers.
        cam.fx, cam.fy = float(K[0, 0]), float(K[1, 1])
        cam.cx, cam.cy = float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5
        size = (int(width), int(height))
        renderer = self._renderers.get(size)
        if renderer is None:
            renderer = self._renderers[size] = self._pr.OffscreenRenderer(*size)
        depth = renderer.render(scene, flags=self._pr.RenderFlags.DEPTH_ONLY)
        return np.asarray(depth, dtype=np.float32)

    def distance_factor(self, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) factor turning a depth image into a distance-from-camera-centre image."""
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        key = (tuple(np.round(K.ravel(), 9)), tuple(shape))
        f = self._rays.get(key)
        if f is None:
            if len(self._rays) > 8:
                self._rays.clear()
            ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
            f = np.sqrt(((xs - K[0, 2]) / K[0, 0]) ** 2 + ((ys - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
            self._rays[key] = f
        return f

    def close(self) -> None:
        for r in self._renderers.values():
            r.delete()
        self._renderers.clear()
        self._scenes.clear()


_DEFAULT_RENDERER: DepthRenderer | None = None


def default_renderer() -> DepthRenderer:
    """A process-wide :class:`DepthRenderer` (created on first use)."""
    global _DEFAULT_RENDERER
    if _DEFAULT_RENDERER is None:
        _DEFAULT_RENDERER = DepthRenderer()
    return _DEFAULT_RENDERER
