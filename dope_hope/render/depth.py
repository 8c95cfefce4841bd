"""Depth images of a triangle model in a pose, rendered the way the BOP toolkit renders them
for VSD.

The toolkit's default renderer (``bop_toolkit_lib/renderer_vispy.py``, mode "depth") draws the
model's triangles (vertex positions as float32, in the model file's units) into a
single-sample framebuffer with a 16-bit depth buffer whose near and far planes are the
nearest and farthest eye-space z of the model's 3D bounding-box corners, reads the depth
buffer back and linearizes it. The projection puts pixel column ``i`` at ``u = i + 0.5`` of
the intrinsics (OpenGL pixel centres). This module does the same with its own OpenGL
program on a headless EGL context (pyrender's EGL platform), with the toolkit's matrix
arithmetic, so that VSD sees the same depth images. (pyrender's own renderer draws with 4x
multisampling into a 24-bit depth buffer with fixed near/far planes, which changes edge
pixels and depth values.)
"""
from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from dope_hope.render.gl import import_pyrender

_VERTEX_SHADER = """#version 330 core
uniform mat4 u_mvp;
in vec3 a_position;
void main() {
    gl_Position = u_mvp * vec4(a_position, 1.0);
}
"""
_FRAGMENT_SHADER = """#version 330 core
out vec4 f_color;
void main() {
    f_color = vec4(0.0, 0.0, 0.0, 1.0);
}
"""


def _bbox_corners(pts: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box of ``pts`` (the toolkit's order and arithmetic)."""
    lo = pts.min(axis=0)
    size = pts.max(axis=0) - lo
    x, y, z = lo
    w, h, d = size
    return np.array([[x, y, z], [x, y, z + d], [x, y + h, z], [x, y + h, z + d],
                     [x + w, y, z], [x + w, y, z + d], [x + w, y + h, z], [x + w, y + h, z + d]])


def calib_projection(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """OpenGL projection of intrinsics ``K`` ("y_down" window coordinates), transposed for
    OpenGL, as the toolkit's ``_calc_calib_proj(K, 0, 0, w, h, near, far)``."""
    depth = float(far - near)
    q = -(far + near) / depth
    qn = -2 * (far * near) / depth
    w, h = width, height
    proj = np.array([[2 * K[0, 0] / w, -2 * K[0, 1] / w, (-2 * K[0, 2] + w) / w, 0],
                     [0, 2 * K[1, 1] / h, (2 * K[1, 2] - h) / h, 0],
                     [0, 0, q, qn],
                     [0, 0, -1, 0]])
    return proj.T


class DepthRenderer:
    """Depth of a triangle model in a pose, as the BOP toolkit's VSD renders it.

    One EGL context (created on first use), one framebuffer per image size, one vertex
    buffer per model (keyed by the identity of its vertex array).
    """

    def __init__(self) -> None:
        self._platform: Any = None
        self._program = None
        self._fbos: dict[tuple[int, int], tuple[int, int, int]] = {}
        self._models: dict[int, tuple] = {}  # id(vertices) -> (vertices, vao, n, corners, buffers)

    def _gl(self):
        import_pyrender()
        from OpenGL import GL  # noqa: PLC0415 (OpenGL only after render.gl chose the platform)

        if self._platform is None:
            from pyrender.platforms.egl import EGLPlatform  # noqa: PLC0415 (only after render.gl chose the platform)

            self._platform = EGLPlatform(1, 1)
            self._platform.init_context()
            from OpenGL.GL import shaders  # noqa: PLC0415 (only after render.gl chose the platform)

            self._program = shaders.compileProgram(
                shaders.compileShader(_VERTEX_SHADER, GL.GL_VERTEX_SHADER),
                shaders.compileShader(_FRAGMENT_SHADER, GL.GL_FRAGMENT_SHADER))
        self._platform.make_current()
        return GL

    def _fbo(self, GL, width: int, height: int) -> int:
        key = (width, height)
        if key not in self._fbos:
            fbo = GL.glGenFramebuffers(1)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
            color, depth = GL.glGenRenderbuffers(2)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, color)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, width, height)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0,
                                         GL.GL_RENDERBUFFER, color)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, depth)
            # vispy's gloo gives a depth render buffer GL_DEPTH_COMPONENT16
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT16, width, height)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT,
                                         GL.GL_RENDERBUFFER, depth)
            if GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER) != GL.GL_FRAMEBUFFER_COMPLETE:
                raise RuntimeError("OpenGL framebuffer for VSD depth rendering is incomplete")
            self._fbos[key] = (fbo, color, depth)
        return self._fbos[key][0]

    def _model(self, GL, model: tuple[np.ndarray, np.ndarray]) -> tuple[int, int, np.ndarray]:
        pts, faces = model
        entry = self._models.get(id(pts))
        if entry is None or entry[0] is not pts:
            if len(self._models) > 64:
                self.close_models(GL)
            vao = GL.glGenVertexArrays(1)
            GL.glBindVertexArray(vao)
            vbo, ebo = GL.glGenBuffers(2)
            positions = np.ascontiguousarray(pts, dtype=np.float32)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
            GL.glBufferData(GL.GL_ARRAY_BUFFER, positions.nbytes, positions, GL.GL_STATIC_DRAW)
            loc = GL.glGetAttribLocation(self._program, "a_position")
            GL.glEnableVertexAttribArray(loc)
            GL.glVertexAttribPointer(loc, 3, GL.GL_FLOAT, GL.GL_FALSE, 12, ctypes.c_void_p(0))
            indices = np.ascontiguousarray(np.asarray(faces).ravel(), dtype=np.uint32)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
            GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, indices.nbytes, indices, GL.GL_STATIC_DRAW)
            GL.glBindVertexArray(0)
            entry = (pts, vao, len(indices), _bbox_corners(np.asarray(pts, dtype=np.float64)),
                     (vbo, ebo))
            self._models[id(pts)] = entry
        return entry[1], entry[2], entry[3]

    def close_models(self, GL) -> None:
        for _, vao, _, _, bufs in self._models.values():
            GL.glDeleteBuffers(2, list(bufs))
            GL.glDeleteVertexArrays(1, [vao])
        self._models.clear()

    def render_depth(self, model: tuple[np.ndarray, np.ndarray], R: np.ndarray, t: np.ndarray,
                     K: np.ndarray, width: int, height: int) -> np.ndarray:
        """(height, width) depth (z, the unit of ``t`` and the model), 0 = no surface.

        Args:
            model: (vertices (N, 3) float, faces (M, 3) int), e.g. from
                :func:`dope_hope.io.meshes.read_ply` (keep the same arrays between calls:
                they are uploaded once).
            R, t: model -> camera (OpenCV), t in the model's unit.
            K: (3, 3) intrinsics (skew ignored, as the toolkit's renderer does).
        """
        GL = self._gl()
        vao, n_idx, corners = self._model(GL, model)
        # The toolkit's matrices: float32 view, near/far from the bbox corners (float64).
        mat_model = np.eye(4, dtype=np.float32)
        mat_view_cv = np.eye(4, dtype=np.float32)
        mat_view_cv[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
        mat_view_cv[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
        cv_to_gl = np.eye(4, dtype=np.float32)
        cv_to_gl[1, 1], cv_to_gl[2, 2] = -1, -1
        mat_view = cv_to_gl.dot(mat_view_cv).T
        corners_ht = np.concatenate((corners, np.ones((corners.shape[0], 1))), axis=1).transpose()
        eye_z = mat_view_cv[2, :].reshape((1, 4)).dot(corners_ht)
        near, far = eye_z.min(), eye_z.max()
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        K_r = np.array([[K[0, 0], 0.0, K[0, 2]], [0.0, K[1, 1], K[1, 2]], [0.0, 0.0, 1.0]])
        mvp = np.dot(np.dot(mat_model, mat_view), calib_projection(K_r, width, height, near, far))

        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fbo(GL, width, height))
        GL.glViewport(0, 0, width, height)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClearDepth(1.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        GL.glUseProgram(self._program)
        GL.glUniformMatrix4fv(GL.glGetUniformLocation(self._program, "u_mvp"), 1, GL.GL_FALSE,
                              np.ascontiguousarray(mvp, dtype=np.float32))
        GL.glBindVertexArray(vao)
        GL.glDrawElements(GL.GL_TRIANGLES, n_idx, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))
        GL.glBindVertexArray(0)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        buf = GL.glReadPixels(0, 0, width, height, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT)
        dep = np.copy(np.frombuffer(buf, np.float32)).reshape(height, width)[::-1, :]
        # The toolkit's linearization (near, far are float64: the result is float64).
        mult = (near * far) / (near - far)
        addi = far / (near - far)
        bg = dep == 1
        dep = mult / (dep + addi)
        dep[bg] = 0
        return dep

    def close(self) -> None:
        """Free the GL objects and the context."""
        if self._platform is not None:
            GL = self._gl()
            self.close_models(GL)
            for fbo, color, depth in self._fbos.values():
                GL.glDeleteRenderbuffers(2, [color, depth])
                GL.glDeleteFramebuffers(1, [fbo])
            self._fbos.clear()
            self._platform.delete_context()
            self._platform = None


_DEFAULT_RENDERER: DepthRenderer | None = None


def default_renderer() -> DepthRenderer:
    """A process-wide :class:`DepthRenderer` (created on first use)."""
    global _DEFAULT_RENDERER
    if _DEFAULT_RENDERER is None:
        _DEFAULT_RENDERER = DepthRenderer()
    return _DEFAULT_RENDERER
