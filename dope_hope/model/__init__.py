"""The network (DopeNetwork, 50-/400-px heads, lite variant) and its checkpoints."""
from dope_hope.model.network import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    DopeNetwork,
    build_model,
    load_backbone_weights,
    normalize_batch,
    normalize_image,
)

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "DopeNetwork",
    "build_model",
    "load_backbone_weights",
    "normalize_batch",
    "normalize_image",
]
