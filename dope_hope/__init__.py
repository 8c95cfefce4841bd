"""dope-hope: DOPE-style 6-DoF pose estimation for the HOPE objects.

Units are metres everywhere inside the package; see ARCHITECTURE.md for the conventions
(camera, pose, cuboid keypoint order, file formats).
"""
from dope_hope.errors import DopeHopeError

__version__ = "0.1.0"
__all__ = ["DopeHopeError", "__version__"]
