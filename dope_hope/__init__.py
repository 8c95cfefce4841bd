"""dope-hope: DOPE-style 6-DoF pose estimation for the HOPE objects.

What a script needs is here; each name is imported on first use, so ``import dope_hope``
stays light (no torch, no OpenGL)::

    import dope_hope
    predictor = dope_hope.DopePredictor("model.pt")        # or an exported .onnx
    detections = predictor.predict(rgb, K, depth=depth)      # list[dope_hope.Detection]
    new = dope_hope.MeshStartPredictor("my_object.obj")    # a new object, no training: the
                                                             # pretrained start on its cuboid
    model = dope_hope.build_model("lite")                   # a fresh lite network (packaged config)
    ketchup = dope_hope.get_object("Ketchup")                # catalog entry (size in metres)
    dope_hope.adapt(["lab.mcap"], "model.pt", "ketchup.obj", "adapt_out")  # a model taught by its
                                                             # own depth-confirmed labels

Units are metres everywhere inside the package; see docs/ARCHITECTURE.md for the conventions
(camera, pose, cuboid keypoint order, file formats).
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from dope_hope.errors import DopeHopeError
from dope_hope.version import __version__

#: Public name -> module that defines it (imported lazily by :func:`__getattr__`).
_LAZY = {
    "DopePredictor": "dope_hope.inference.predictor",
    "predict_many": "dope_hope.inference.predictor",
    "MeshStartPredictor": "dope_hope.inference.mesh_start",
    "Detection": "dope_hope.inference.detection",
    "load_model": "dope_hope.model.checkpoint",
    "build_model": "dope_hope.model.network",
    "get_object": "dope_hope.catalog",
    "HOPE_OBJECTS": "dope_hope.catalog",
    "adapt": "dope_hope.adaptation.run",
}

__all__ = ["DopeHopeError", "Detection", "DopePredictor", "HOPE_OBJECTS", "MeshStartPredictor", "__version__",
           "adapt", "build_model", "get_object", "load_model", "predict_many"]

if TYPE_CHECKING:
    from dope_hope.adaptation.run import adapt
    from dope_hope.catalog import HOPE_OBJECTS, get_object
    from dope_hope.inference.detection import Detection
    from dope_hope.inference.mesh_start import MeshStartPredictor
    from dope_hope.inference.predictor import DopePredictor, predict_many
    from dope_hope.model.checkpoint import load_model
    from dope_hope.model.network import build_model


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'dope_hope' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
