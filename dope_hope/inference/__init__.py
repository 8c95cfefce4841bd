"""Inference: image (+ K, depth) -> detections.

Modules: ``preprocess`` (image layout, working size, letterbox, normalization: the one
definition shared with export's INT8 calibration), ``backends`` (the :class:`MapBackend`
protocol and the PyTorch backend), ``onnx_backend`` (onnxruntime, kept apart), ``pnp``
(PnP and the multi-hypothesis pose search), ``detection`` (:class:`Detection`), ``object_geometry``
(one object's cuboid, mesh and surface points), ``predictor`` (:class:`DopePredictor`, which
runs them in order, object by object, and hands poses to :mod:`dope_hope.refine`).
"""
