"""ONNX export: ``to_onnx`` (graph, layouts, metadata, verification), ``int8`` (static
quantization with calibration), ``compare`` (map and keypoint deviation between two models),
``pipeline`` (:func:`export_checkpoint`, what ``dope-hope export`` runs).
"""
