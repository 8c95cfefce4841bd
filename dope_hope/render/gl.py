"""Headless OpenGL for pyrender: the one place that prepares it.

Import pyrender only through :func:`import_pyrender`. It

1. selects Mesa EGL (``PYOPENGL_PLATFORM=egl``) unless the user set ``PYOPENGL_PLATFORM``
   already. EGL works on a fresh Debian machine without a display and without an apt step;
   OSMesa does not work with the PyOpenGL 3.1.0 that pyrender 0.1.45 pins.
2. restores ``np.infty``, which numpy 2 removed and which pyrender 0.1.45 still uses for
   scene bounds and shadow maps (``pyrender/scene.py``, ``pyrender/renderer.py``). The alias
   is the same float as ``np.inf``; nothing else is patched.
3. loads triton's LLVM first when triton is installed (it comes with the CUDA builds of
   torch, and torchvision imports it). Mesa's EGL renderer (llvmpipe) loads the system LLVM;
   loading triton's own LLVM *after* it crashes the process (a segmentation fault when a
   process that rendered later imports torchvision: evaluation's VSD then a model, a test
   session), while the other order is fine.
"""
from __future__ import annotations

import importlib.util
import os
from types import ModuleType

import numpy as np


def configure_headless_gl() -> None:
    """Choose EGL unless the user chose a platform; must run before OpenGL is imported."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if importlib.util.find_spec("triton") is not None:
        import triton._C.libtriton  # noqa: F401, PLC0415  (before Mesa's LLVM: step 3 above)
    if not hasattr(np, "infty"):
        np.infty = np.inf  # type: ignore[attr-defined]  # pyrender 0.1.45 with numpy >= 2


def import_pyrender() -> ModuleType:
    """Return the pyrender module, headless-ready."""
    configure_headless_gl()
    import pyrender  # noqa: PLC0415  (import after the platform is chosen)

    return pyrender
