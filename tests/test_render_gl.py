"""The headless OpenGL preparation of dope_hope.render.gl."""
from __future__ import annotations

import ctypes
import os

import pytest

from dope_hope.render.gl import configure_headless_gl


def test_pyopengl_takes_this_pythons_byref_type(monkeypatch: pytest.MonkeyPatch):
    """Python 3.12 renamed ctypes' byref type (_ctypes.CArgObject); PyOpenGL 3.1.0 knows only
    builtins.CArgObject, and then every GL call returning through byref fails. After the
    preparation, the handler lists this Python's name, whichever PyOpenGL lists it already."""
    configure_headless_gl()
    from OpenGL import plugins

    handler = plugins.FormatHandler.by_name("ctypesparameter")
    byref_type = type(ctypes.byref(ctypes.c_int()))
    name = f"{byref_type.__module__}.{byref_type.__name__}"
    without = [n for n in handler.check if n != name]
    monkeypatch.setattr(handler, "check", without)  # as PyOpenGL 3.1.0 on Python 3.12
    assert plugins.FormatHandler.match(byref_type) is None
    configure_headless_gl()
    assert plugins.FormatHandler.match(byref_type) is handler
    assert handler.check[: len(without)] == without  # the names it had are kept


def test_pyglet_is_headless_unless_the_user_chose(monkeypatch: pytest.MonkeyPatch):
    """pyrender imports pyglet's window module, which loads X11 libraries unless pyglet is
    headless: on a GPU server without them the import fails."""
    monkeypatch.delenv("PYGLET_HEADLESS", raising=False)
    configure_headless_gl()
    assert os.environ["PYGLET_HEADLESS"] == "True"
    monkeypatch.setenv("PYGLET_HEADLESS", "False")
    configure_headless_gl()
    assert os.environ["PYGLET_HEADLESS"] == "False"
