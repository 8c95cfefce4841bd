"""A textured mesh rendered unlit (its own texture colours) at a pose, into a small image.

What an appearance check compares with a camera image: :class:`TexturedRenderer` keeps one
offscreen context and the mesh on it, and renders it at any pose (OpenCV convention,
``x_c = R x + t``) through any pinhole K, flat shaded (the base colour texture, no lights), so
the picture depends on the texture and the pose only.
"""
from __future__ import annotations

import numpy as np

from dope_hope.render.gl import close_offscreen, gl_camera, import_pyrender, pose_gl


class TexturedRenderer:
    """One mesh, rendered unlit at poses.

    Args:
        mesh: a ``trimesh.Trimesh`` in metres (its texture or vertex colours kept, as
            :func:`dope_hope.io.meshes.load_mesh` returns it).
        width, height: render size, pixels.
    """

    def __init__(self, mesh, width: int, height: int):
        pyrender = import_pyrender()
        self._pyrender = pyrender
        self.width, self.height = int(width), int(height)
        self._r = pyrender.OffscreenRenderer(self.width, self.height)
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[1.0, 1.0, 1.0])
        self._node = self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
        self._camera = self._scene.add(gl_camera(np.eye(3), 0.01, 100.0), pose=np.eye(4))
        extent = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
        self._radius = max(extent / 2.0, 1e-3)

    def render(self, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((height, width, 3) uint8 colours, (height, width) bool mask) of the mesh at pose
        R (3, 3), t (3,) m through intrinsics K (3, 3) of this render size."""
        if self._r is None:
            raise RuntimeError("TexturedRenderer is closed")
        depth = float(np.asarray(t)[2])
        znear = max(1e-3, depth - 2.0 * self._radius)
        self._camera.camera = gl_camera(np.asarray(K, dtype=np.float64), znear, depth + 2.0 * self._radius)
        self._scene.set_pose(self._node, pose_gl(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)))
        color, z = self._r.render(self._scene, flags=self._pyrender.RenderFlags.FLAT)
        return np.ascontiguousarray(color[..., :3]), z > 0

    def close(self) -> None:
        """Free the GL context (:func:`~dope_hope.render.gl.close_offscreen`)."""
        if self._r is not None:
            r, self._r = self._r, None
            close_offscreen(r)

    def __enter__(self) -> TexturedRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
