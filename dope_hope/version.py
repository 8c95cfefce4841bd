"""The package version (the bottom layer: checkpoints, ONNX metadata and datasets record it)."""

__version__ = "0.1.0"
