"""The generator's settings: the synth config (defaults + user file), sizes and shards."""
from __future__ import annotations

import os
from typing import Any

from dope_hope.config import check_known_keys, config_path, load_yaml, merge
from dope_hope.errors import ConfigError

#: Name of the default config (configs/synth.yaml).
DEFAULT_CONFIG = "synth"

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
    ("depth_noise", "edge_width_px"),
]


def load_synth_config(config: str | os.PathLike | dict[str, Any] | None = None) -> dict[str, Any]:
    """The synth config: ``configs/synth.yaml`` with ``config`` deep-merged over it.

    Args:
        config: None or "synth" (the defaults), a config name or YAML path, or a dict of
            overrides (same nesting as the file).

    Raises:
        ConfigError / InputFileError: unknown name, unreadable file or an invalid range.
    """
    base = packaged_synth_config()
    if config is None or (isinstance(config, str) and config == DEFAULT_CONFIG):
        cfg = base
    elif isinstance(config, dict):
        check_known_keys(config, base, "synth config")
        cfg = merge(base, config)
    else:
        path = config_path(config)
        override = load_yaml(path)
        check_known_keys(override, base, f"synth config {path}")
        cfg = merge(base, override)
    validate_synth_config(cfg)
    return cfg


def packaged_synth_config() -> dict[str, Any]:
    """``configs/synth.yaml``: every key a synth config may set."""
    return load_yaml(config_path(DEFAULT_CONFIG))


def validate_synth_config(cfg: dict[str, Any]) -> None:
    """Raise ConfigError naming the first invalid key."""
    for section, key in _RANGES:
        try:
            lo, hi = cfg[section][key]
            bad = not (float(lo) <= float(hi))
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"synth config: {section}.{key} must be a [min, max] pair") from None
        if bad:
            raise ConfigError(f"synth config: {section}.{key} has min > max ({lo} > {hi})")
    if cfg["target"]["count"][0] < 1:
        raise ConfigError("synth config: target.count must start at 1 or more")
    if cfg["target"]["distance_m"][0] <= cfg["camera"]["znear"]:
        raise ConfigError("synth config: target.distance_m must lie beyond camera.znear")
    base = int(cfg["output"]["seg_distractor_base"])
    if not cfg["target"]["count"][1] < base or base + cfg["distractors"]["count"][1] + \
            cfg["target"]["count"][1] > 255:
        raise ConfigError("synth config: seg ids must fit in uint8: target.count[1] < "
                          "output.seg_distractor_base and base + distractors + occluders <= 255")
    for section, key in (("distractors", "primitives"), ("lights", "types"),
                         ("background", "procedural_weights"), ("procedural", "categories")):
        weights = cfg[section][key]
        if not isinstance(weights, dict) or not any(float(v) > 0 for v in weights.values()):
            raise ConfigError(f"synth config: {section}.{key} needs at least one positive weight")
    from dope_hope.catalog import CATEGORIES

    unknown = sorted(set(cfg["procedural"]["categories"]) - set(CATEGORIES))
    if unknown:
        raise ConfigError(f"synth config: procedural.categories: unknown {', '.join(unknown)}; "
                          f"known: {', '.join(CATEGORIES)}")
    jitter = cfg["procedural"]["size_jitter"]
    if not isinstance(jitter, (int, float)) or not 0 <= jitter < 1:
        raise ConfigError(f"synth config: procedural.size_jitter must be a number in [0, 1), got {jitter!r}")
    px = cfg["procedural"]["texture_px"]
    if isinstance(px, bool) or not isinstance(px, int) or not 16 <= px <= 4096:
        raise ConfigError(f"synth config: procedural.texture_px must be a whole number in 16..4096, got {px!r}")
    if not isinstance(cfg["procedural"]["canonical_labels"], bool):
        raise ConfigError("synth config: procedural.canonical_labels must be true or false")


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
