"""The generator's settings: the synth config (defaults + user file), sizes and shards.

The packaged ``dope_hope/configs/synth.yaml`` documents every key and gives its default; the
settings classes (:class:`SynthSettings`, one frozen :class:`~dope_hope.config.SectionSettings`
per section and nested section, named after it: ``SynthTargetSettings``,
``SynthBackgroundClutterSettings`` ...) are generated from it, so the defaults have that one
owner. The generator reads them as attributes (``cfg.target.count``); a section of named
weights (``distractors.primitives``, ``lights.types`` ...) is read as a mapping with
``to_dict()``.
Each key's value must be of its default's kind (a number, a whole number, true/false, a name,
a list of the same length; ``depth_noise.stereo_fx_px`` may be null), and the whole config
passes :func:`validate_synth_config` (ranges, probabilities, bounds, seg ids).
"""
from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from typing import Any

from dope_hope.config import SectionSettings, config_path, load_settings, load_yaml
from dope_hope.errors import ConfigError
from dope_hope.synth.sensor import EFFECT_PROBS

#: Name of the default config (configs/synth.yaml).
DEFAULT_CONFIG = "synth"
#: Overrides that switch off the clutter backgrounds, the hard negatives and the sensor
#: artefacts (the generator's frames before they existed, e.g. for models trained on those).
PLAIN_OVERRIDES: dict[str, Any] = {
    "background": {"clutter_prob": 0.0},
    "hard_negatives": {"count": [0, 0]},
    "post": {k: 0.0 for k in EFFECT_PROBS},
}

# (section, key) pairs that must be [min, max] ranges with min <= max.
_RANGES = [
    ("target", "count"), ("target", "distance_m"), ("target", "truncation_offset"),
    ("target", "roughness"), ("target", "brightness"),
    ("distractors", "count"), ("distractors", "distance_m"), ("distractors", "size_m"),
    ("distractors", "texture_tile_m"), ("distractors", "metallic"), ("distractors", "roughness"),
    ("distractors", "tint"), ("distractors", "occluder_offset"), ("distractors", "occluder_radius"),
    ("distractors", "occluder_depth"),
    ("lights", "count"), ("lights", "spot_outer_deg"), ("lights", "spot_inner_ratio"),
    ("lights", "saturation"), ("lights", "ambient"),
    ("background", "crop_scale"),
    ("post", "brightness"), ("post", "contrast"), ("post", "saturation"), ("post", "hue_deg"),
    ("post", "blur_sigma_px"), ("post", "noise_sigma"),
    ("post", "defocus_radius_px"), ("post", "motion_blur_px"), ("post", "chromatic_px"),
    ("post", "vignetting"), ("post", "exposure_ev"), ("post", "white_balance"),
    ("post", "shot_noise"), ("post", "read_noise"), ("post", "jpeg_quality"),
    ("background", "clutter", "count"), ("background", "clutter", "size"),
    ("background", "clutter", "ambient"), ("background", "clutter", "blur_sigma_px"),
    ("hard_negatives", "count"), ("hard_negatives", "size_jitter"), ("hard_negatives", "shuffle_grid"),
    ("depth_noise", "edge_width_px"),
]
# Keys that must be probabilities in [0, 1].
_PROBABILITIES = [
    ("target", "truncation_prob"), ("distractors", "mesh_prob"), ("distractors", "keep_texture_prob"),
    ("distractors", "texture_prob"), ("distractors", "occluder_prob"),
    ("background", "procedural_prob_with_images"), ("background", "flip_prob"), ("background", "vflip_prob"),
    ("background", "clutter_prob"), ("background", "clutter", "photo_texture_prob"),
    ("background", "clutter", "shadow_prob"), ("hard_negatives", "same_shape_prob"),
    ("post", "jitter_prob"), ("post", "blur_prob"), ("post", "noise_prob"),
    ("post", "defocus_prob"), ("post", "motion_blur_prob"), ("post", "chromatic_prob"),
    ("post", "vignetting_prob"), ("post", "exposure_prob"), ("post", "shot_noise_prob"), ("post", "jpeg_prob"),
]
# Ranges that must lie within [lo, hi] (None: unbounded on that side).
_BOUNDS = [
    (("post", "jpeg_quality"), 1, 100), (("post", "defocus_radius_px"), 0, None),
    (("post", "motion_blur_px"), 0, None), (("post", "chromatic_px"), 0, None),
    (("post", "vignetting"), 0, 0.95), (("post", "white_balance"), 0, None),
    (("post", "shot_noise"), 0, None), (("post", "read_noise"), 0, None),
    (("background", "clutter", "count"), 0, None), (("background", "clutter", "size"), 0, None),
    (("background", "clutter", "ambient"), 0, 1), (("background", "clutter", "blur_sigma_px"), 0, None),
    (("hard_negatives", "count"), 0, None), (("hard_negatives", "size_jitter"), 0.01, None),
    (("hard_negatives", "shuffle_grid"), 1, None),
]


def _lookup(cfg: SectionSettings, path: tuple[str, ...]) -> Any:
    """The value of the dotted key ``path`` of the settings ``cfg``."""
    node: Any = cfg
    for part in path:
        node = getattr(node, part)
    return node


#: Keys that may also be null (their meaning: see synth.yaml).
_NULLABLE = {("depth_noise", "stereo_fx_px")}


def _kind_rule(default: Any, nullable: bool) -> Any:
    """The rule of a key whose default is ``default``: a value of the same kind, kept as given
    (a list: the same length, numbers where the default has numbers)."""
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def checked(value: Any, name: str) -> Any:
        if value is None and nullable:
            return value
        if isinstance(default, bool):
            ok = isinstance(value, bool)
            kind = "true or false"
        elif isinstance(default, int):
            ok = number(value) and value == int(value)
            kind = "a whole number"
        elif isinstance(default, float):
            ok = number(value)
            kind = "a finite number"
        elif isinstance(default, str):
            ok = isinstance(value, str)
            kind = "a name"
        else:
            ok = isinstance(value, (list, tuple)) and len(value) == len(default) and all(
                number(v) or not number(d) for v, d in zip(value, default))
            kind = f"a list of {len(default)} numbers"
        if not ok:
            raise ConfigError(f"{name} must be {kind}{' or null' if nullable else ''}, got {value!r}")
        return list(value) if isinstance(value, tuple) else value
    return checked


def _section_class(name: str, defaults: Mapping[str, Any], path: tuple[str, ...]) -> type[SectionSettings]:
    """A frozen settings class of the section ``defaults`` (nested sections: nested classes)."""
    spec, rules = [], {}
    for key, value in defaults.items():
        if isinstance(value, dict):
            nested = _section_class(key, value, (*path, key))
            spec.append((key, nested, dataclasses.field(default_factory=nested)))
        else:
            frozen = tuple(value) if isinstance(value, list) else value
            spec.append((key, type(frozen), dataclasses.field(default=frozen)))
            rules[key] = _kind_rule(value, (*path, key) in _NULLABLE)
    cls_name = "Synth" + "".join(part.title() for part in path for part in part.split("_")) + \
        ("Settings" if path else "Sections")
    cls = dataclasses.make_dataclass(cls_name, spec, bases=(SectionSettings,), frozen=True,
                                     namespace={"SECTION": ".".join(path), "RULES": rules,
                                                "__module__": __name__,
                                                "__doc__": f"The synth config's {'.'.join(path) or 'sections'} "
                                                           "(defaults: dope_hope/configs/synth.yaml)."})
    if cls_name in globals():
        raise RuntimeError(f"synth.yaml: two sections make the settings class {cls_name}")
    globals()[cls_name] = cls  # importable by name: the settings pickle to the worker processes
    return cls


def _synth_settings_class() -> type[SectionSettings]:
    base = _section_class("synth", load_yaml(config_path(DEFAULT_CONFIG)), ())

    def __post_init__(self: Any) -> None:
        base.__post_init__(self)
        validate_synth_config(self)

    return dataclasses.make_dataclass("SynthSettings", [], bases=(base,), frozen=True,
                                      namespace={"__post_init__": __post_init__, "__module__": __name__,
                                                 "__doc__": "The synth config: every section of "
                                                            "dope_hope/configs/synth.yaml, over its defaults."})


def load_synth_config(config: str | os.PathLike | Mapping[str, Any] | SectionSettings | None = None,
                      assignments: list[str] | tuple[str, ...] = ()) -> Any:
    """The synth config (a frozen :data:`SynthSettings`, each section an attribute):
    ``configs/synth.yaml`` with ``config`` deep-merged over it, then the ``section.key=value``
    items of ``assignments`` (:func:`~dope_hope.config.load_settings`).

    Args:
        config: None or "synth" (the defaults), a config name or YAML path, a dict of
            overrides (same nesting as the file), or settings already loaded (returned as
            they are when there are no ``assignments``).

    Raises:
        ConfigError / InputFileError: unknown name or key, unreadable file, a bad value or an
            invalid range.
    """
    if isinstance(config, SynthSettings) and not assignments:
        return config
    if isinstance(config, SectionSettings):
        config = config.to_dict()
    if isinstance(config, str) and config == DEFAULT_CONFIG:
        config = None
    return load_settings(SynthSettings, config, assignments)


def packaged_synth_config() -> dict[str, Any]:
    """``configs/synth.yaml``: every key a synth config may set, with its default."""
    return SynthSettings().to_dict()


def validate_synth_config(cfg: Any) -> None:
    """Raise ConfigError naming the first invalid key of the synth settings ``cfg`` (each
    value already of its default's kind)."""
    for path in _RANGES:
        name = ".".join(path)
        try:
            lo, hi = _lookup(cfg, path)
            bad = not (float(lo) <= float(hi))
        except (AttributeError, TypeError, ValueError):
            raise ConfigError(f"{name} must be a [min, max] pair") from None
        if bad:
            raise ConfigError(f"{name} has min > max ({lo} > {hi})")
    for path, lo, hi in _BOUNDS:
        a, b = (float(v) for v in _lookup(cfg, path))
        if (lo is not None and a < lo) or (hi is not None and b > hi):
            raise ConfigError(f"{'.'.join(path)} must lie in "
                              f"[{lo}, {'inf' if hi is None else hi}], got [{a:g}, {b:g}]")
    for path in _PROBABILITIES:
        try:
            p = float(_lookup(cfg, path))
            bad = not 0.0 <= p <= 1.0
        except (AttributeError, TypeError, ValueError):
            bad = True
        if bad:
            raise ConfigError(f"{'.'.join(path)} must be a probability in [0, 1]")
    if not 0.05 <= float(cfg.background.clutter.resolution) <= 1.0:
        raise ConfigError("background.clutter.resolution must lie in [0.05, 1]")
    for path in (("background", "clutter", "texture_px"), ("background", "clutter", "texture_pool"),
                 ("hard_negatives", "texture_px")):
        v = _lookup(cfg, path)
        if isinstance(v, bool) or not isinstance(v, int) or v < (4 if path[-1] == "texture_px" else 1):
            raise ConfigError(f"{'.'.join(path)} must be a whole number "
                              f"(>= {4 if path[-1] == 'texture_px' else 1}), got {v!r}")
    if cfg.target.count[0] < 0:
        raise ConfigError("target.count must start at 0 or more")
    if cfg.target.distance_m[0] <= cfg.camera.znear:
        raise ConfigError("target.distance_m must lie beyond camera.znear")
    base = int(cfg.output.seg_distractor_base)
    if not cfg.target.count[1] < base or base + cfg.distractors.count[1] + \
            cfg.target.count[1] + cfg.hard_negatives.count[1] > 255:
        raise ConfigError("seg ids must fit in uint8: target.count[1] < "
                          "output.seg_distractor_base and base + distractors + occluders "
                          "(target.count[1]) + hard_negatives.count[1] <= 255")
    for path in (("distractors", "primitives"), ("lights", "types"), ("background", "procedural_weights"),
                 ("background", "clutter", "kinds"), ("hard_negatives", "textures"), ("procedural", "categories")):
        weights = _lookup(cfg, path).to_dict()
        if not any(float(v) > 0 for v in weights.values()):
            raise ConfigError(f"{'.'.join(path)} needs at least one positive weight")
    from dope_hope.synth.objects import SHAPE_LABELS  # noqa: PLC0415 (the procedural shapes' module brings trimesh: only when a config is checked)

    unknown = sorted(set(cfg.procedural.categories.to_dict()) - set(SHAPE_LABELS))
    if unknown:
        raise ConfigError(f"procedural.categories: unknown {', '.join(unknown)}; "
                          f"known: {', '.join(SHAPE_LABELS)}")
    scale = cfg.procedural.scale
    if not (isinstance(scale, list) and len(scale) == 2 and all(isinstance(v, (int, float)) and
            not isinstance(v, bool) for v in scale) and 0.05 <= scale[0] <= scale[1] <= 20):
        raise ConfigError(f"procedural.scale must be [low, high] with 0.05 <= low <= "
                          f"high <= 20, got {scale!r}")
    jitter = cfg.procedural.size_jitter
    if not isinstance(jitter, (int, float)) or not 0 <= jitter < 1:
        raise ConfigError(f"procedural.size_jitter must be a number in [0, 1), got {jitter!r}")
    px = cfg.procedural.texture_px
    if isinstance(px, bool) or not isinstance(px, int) or not 16 <= px <= 4096:
        raise ConfigError(f"procedural.texture_px must be a whole number in 16..4096, got {px!r}")
    if not isinstance(cfg.procedural.canonical_labels, bool):
        raise ConfigError("procedural.canonical_labels must be true or false")


#: The synth config's settings class (generated from ``configs/synth.yaml``).
SynthSettings = _synth_settings_class()


def parse_size(text: str | tuple[int, int]) -> tuple[int, int]:
    """"640x480" -> (640, 480) (width, height); a pair passes through."""
    if isinstance(text, (tuple, list)):
        w, h = (int(v) for v in text)
    else:
        try:
            w, h = (int(v) for v in str(text).lower().split("x"))
        except ValueError:
            raise ConfigError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise ConfigError(f"--size {w}x{h}: width and height must lie in 8..8192")
    return w, h


def parse_shard(text: str | tuple[int, int] | None) -> tuple[int, int]:
    """"i/n" -> (i, n) with 0 <= i < n; None -> (0, 1)."""
    if text is None:
        return 0, 1
    if isinstance(text, (tuple, list)):
        i, n = (int(v) for v in text)
    else:
        try:
            i, n = (int(v) for v in str(text).split("/"))
        except ValueError:
            raise ConfigError(f"--shard {text!r}: expected i/n, e.g. 0/4") from None
    if n < 1 or not 0 <= i < n:
        raise ConfigError(f"--shard {i}/{n}: need 0 <= i < n")
    return i, n
