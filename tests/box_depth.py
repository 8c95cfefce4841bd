"""Test helper (not a test file): the exact box depth and surface points of the library
(:mod:`dope_hope.render.box`), under the names the tests import."""
from dope_hope.render.box import box_surface_points, render_box_depth

__all__ = ["box_surface_points", "render_box_depth"]
