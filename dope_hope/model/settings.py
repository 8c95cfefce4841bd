"""The ``model`` and ``input`` sections of a training recipe: which network :func:`~dope_hope.model.network.build_model`
builds and the input it is trained on (torch-free, so that commands check a recipe before
importing torch)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dope_hope.config import SectionSettings, at_least, each, one_of, or_none, section, whole_number
from dope_hope.errors import ConfigError


def _path_text(value: Any, name: str) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{name} must be a file path, got {value!r}")
    return value


@dataclass(frozen=True)
class DecoderSettings(SectionSettings):
    """``model.decoder`` (head 400): trunk features squeezed to reduce_channels once; channels:
    widths after the three stride-2 transposed convolutions; stages: all (every stage decoded)
    or last (only the last; the others bilinearly upsampled)."""

    SECTION = "model.decoder"
    RULES = {"reduce_channels": at_least(1), "channels": each(at_least(1)), "stages": one_of("all", "last")}

    reduce_channels: int = 32
    channels: tuple[int, ...] = (32, 16, 16)
    stages: str = "all"


@dataclass(frozen=True)
class LiteSettings(SectionSettings):
    """``model.lite`` (arch lite, :class:`~dope_hope.model.lite.LiteTrunk`): encoder width (widths
    w, 2w, 4w, 4w, 4w at strides 2..32), feature_channels, stage_channels."""

    SECTION = "model.lite"
    RULES = {"width": at_least(1), "feature_channels": at_least(1), "stage_channels": at_least(1)}

    width: int = 24
    feature_channels: int = 96
    stage_channels: int = 64


@dataclass(frozen=True)
class ModelSettings(SectionSettings):
    """The ``model`` section: arch dope (official layout, VGG19 trunk) or lite; head 50 (maps at
    stride 8), 400 (full resolution, dope) or 100 (stride 4, lite); stages (dope 1..6, lite
    1..4); decoder (head 400) and lite (arch lite) options; num_objects: a belief/affinity
    group per object; backbone_weights: an optional LOCAL torchvision VGG19 state dict (arch dope)."""

    SECTION = "model"
    RULES = {"arch": one_of("dope", "lite"), "head": at_least(1),
             "stages": at_least(1), "num_objects": at_least(1), "backbone_weights": or_none(_path_text)}

    arch: str = "dope"
    head: int = 50
    stages: int = 6
    decoder: DecoderSettings = section(DecoderSettings)
    lite: LiteSettings = section(LiteSettings)
    num_objects: int = 1
    backbone_weights: str | None = None


def _input_size(value: Any, name: str) -> tuple[int, int]:
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(f"{name} must be [H, W], got {value!r}")
    h, w = (whole_number(v, name, 8) for v in value)
    if h % 8 or w % 8:
        raise ConfigError(f"{name} {list(value)} must be positive multiples of 8")
    return h, w


@dataclass(frozen=True)
class InputSettings(SectionSettings):
    """The ``input`` section: size [H, W] of the training input, pixels, multiples of 8;
    normalization of its RGB (imagenet: RGB/255 minus the ImageNet mean, over its std)."""

    SECTION = "input"
    RULES = {"size": _input_size, "normalization": one_of("imagenet")}

    size: tuple[int, int] = (400, 400)
    normalization: str = "imagenet"
