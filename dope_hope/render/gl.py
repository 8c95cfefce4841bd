"""Headless OpenGL for pyrender: the one place that prepares it.

Import pyrender only through :func:`import_pyrender`. It

1. selects Mesa EGL (``PYOPENGL_PLATFORM=egl``) unless the user set ``PYOPENGL_PLATFORM``
   already. EGL works on a fresh Debian machine without a display and without an apt step;
   OSMesa does not work with the PyOpenGL 3.1.0 that pyrender 0.1.45 pins. It also puts
   pyglet in its headless mode (``PYGLET_HEADLESS``, unless set): pyrender imports pyglet's
   window module for its viewer, which otherwise loads X11 libraries, and fails where they
   are missing (a GPU server or container with EGL and no X: "'NoneType' object has no
   attribute 'XRenderFindVisualFormat'"). The frames rendered are the same.
2. restores ``np.infty``, which numpy 2 removed and which pyrender 0.1.45 still uses for
   scene bounds and shadow maps (``pyrender/scene.py``, ``pyrender/renderer.py``). The alias
   is the same float as ``np.inf``; nothing else is patched.
3. loads triton's LLVM first when triton is installed (it comes with the CUDA builds of
   torch, and torchvision imports it). Mesa's EGL renderer (llvmpipe) loads the system LLVM;
   loading triton's own LLVM *after* it crashes the process (a segmentation fault when a
   process that rendered later imports torchvision: evaluation's VSD then a model, a test
   session), while the other order is fine.
4. teaches PyOpenGL 3.1.0 the name Python 3.12 gives ctypes' ``byref`` type
   (``_ctypes.CArgObject``; earlier Pythons: ``builtins.CArgObject``, the one name 3.1.0
   knows). Without it every GL call that returns through ``byref`` (``glGenTextures`` in
   pyrender's first render) fails on Python >= 3.12 with "No array-type handler for type
   _ctypes.type". PyOpenGL 3.1.7 adds the same name to the same handler; pyrender 0.1.45
   pins 3.1.0.
"""
from __future__ import annotations

import ctypes
import importlib.util
import os
from types import ModuleType

import numpy as np

#: OpenCV camera frame -> OpenGL camera frame.
CV_TO_GL = np.diag([1.0, -1.0, -1.0])


def configure_headless_gl() -> None:
    """Choose EGL unless the user chose a platform; must run before OpenGL is imported."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("PYGLET_HEADLESS", "True")
    if importlib.util.find_spec("triton") is not None:
        import triton._C.libtriton  # noqa: F401, PLC0415  (before Mesa's LLVM: step 3 above)
    if not hasattr(np, "infty"):
        np.infty = np.inf  # type: ignore[attr-defined]  # pyrender 0.1.45 with numpy >= 2
    _name_byref_type_for_pyopengl()


def _name_byref_type_for_pyopengl() -> None:
    """Step 4 of the module docstring: list this Python's name of ctypes' ``byref`` type
    among the types PyOpenGL's ctypes-parameter handler takes (no change where it is listed)."""
    from OpenGL import plugins  # noqa: PLC0415  (the package only: no platform is loaded)

    handler = plugins.FormatHandler.by_name("ctypesparameter")
    byref_type = type(ctypes.byref(ctypes.c_int()))
    name = f"{byref_type.__module__}.{byref_type.__name__}"
    if handler is not None and handler.check and name not in handler.check:
        handler.check = [*handler.check, name]


def import_pyrender() -> ModuleType:
    """Return the pyrender module, headless-ready."""
    configure_headless_gl()
    import pyrender  # noqa: PLC0415  (import after the platform is chosen)

    return pyrender


def close_offscreen(renderer) -> None:
    """Free a ``pyrender.OffscreenRenderer``'s GL objects and context.

    pyrender's ``OffscreenRenderer.delete`` also calls ``eglTerminate`` on the display,
    which is shared by every context of the process (EGL displays are per device), so it
    would break other live renderers (e.g. two generators in one test session). Here the
    context is destroyed and the display left initialized; it goes away with the process.
    """
    platform = renderer._platform
    display = getattr(platform, "_egl_display", None)
    context = getattr(platform, "_egl_context", None)
    if display is None or context is None:  # not EGL: pyrender's own cleanup is safe
        renderer.delete()
        return
    # EGL only where a context is released
    from OpenGL.EGL import (  # noqa: PLC0415  (after the platform is chosen)
        EGL_NO_CONTEXT,
        EGL_NO_SURFACE,
        eglDestroyContext,
        eglMakeCurrent,
    )

    platform.make_current()
    renderer._renderer.delete()
    eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
    eglDestroyContext(display, context)
    # Detach everything so that pyrender's __del__ hooks (which would call eglTerminate)
    # find nothing to delete.
    platform._egl_context = None
    platform._egl_display = None
    renderer._renderer = None
    renderer._platform = None


def pose_gl(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) node pose in the OpenGL camera frame of an OpenCV pose (R, t)."""
    T = np.eye(4)
    T[:3, :3] = CV_TO_GL @ R
    T[:3, 3] = CV_TO_GL @ t
    return T


def gl_camera(K: np.ndarray, znear: float, zfar: float, ox: float = 0.0, oy: float = 0.0):
    """pyrender camera of OpenCV intrinsics K (3, 3) (pixel centres at integers), its principal
    point shifted by (ox, oy) px (a canvas that starts elsewhere than the image)."""
    pyrender = import_pyrender()
    return pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5 + ox,
                                     cy=K[1, 2] + 0.5 + oy, znear=znear, zfar=zfar)
