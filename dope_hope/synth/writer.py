"""Writing generated frames: image files first, the JSON last, each one atomically.

A frame is complete exactly when its ``NNNNNN.json`` exists: the JSON is renamed into place
only after the RGB, depth and segmentation images are, so an interrupted run never leaves a
JSON without its images, and a resumed run skips frames whose JSON exists.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.config import differing_keys
from dope_hope.errors import ConfigError
from dope_hope.io import atomic
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_depth_mm, write_rgb

#: Dataset-level settings file (no image beside it, so frame listings ignore it).
INFO_NAME = "_synth_info.json"


def frame_stem(index: int) -> str:
    """Frame file stem, e.g. 7 -> "000007"."""
    return f"{int(index):06d}"


def frame_paths(out_dir: str | os.PathLike, index: int) -> dict[str, Path]:
    """Paths of frame ``index``: keys rgb, depth, seg, json."""
    d = Path(out_dir)
    s = frame_stem(index)
    return {"rgb": d / f"{s}.png", "depth": d / f"{s}.depth.png", "seg": d / f"{s}.seg.png",
            "json": d / f"{s}.json"}


def is_complete(out_dir: str | os.PathLike, index: int) -> bool:
    """True when frame ``index`` was written completely (its JSON exists)."""
    return frame_paths(out_dir, index)["json"].is_file()


def remove_stale_frame_temporaries(out_dir: str | os.PathLike, indices: set[int]) -> int:
    """Delete temporary files an interrupted run left for the given frames; returns how many.

    Only call this when no other process writes the same frames.
    """
    def of_frames(stem: str) -> bool:
        head = stem.split(".", 1)[0]
        return head.isdigit() and int(head) in indices

    return atomic.remove_stale_temporaries(out_dir, of_frames)


def write_frame(out_dir: str | os.PathLike, index: int, rgb: np.ndarray, depth_m: np.ndarray,
                seg: np.ndarray, frame: FrameAnnotation, extra: dict[str, Any] | None = None) -> Path:
    """Write one frame: RGB png, uint16 mm depth png, uint8 seg png, then the JSON.

    Returns:
        The JSON path.
    """
    paths = frame_paths(out_dir, index)
    write_rgb(paths["rgb"], rgb)
    write_depth_mm(paths["depth"], depth_m)
    write_rgb(paths["seg"], np.ascontiguousarray(seg, dtype=np.uint8))
    frame.source = paths["json"]
    frame.image_path, frame.depth_path, frame.seg_path = paths["rgb"], paths["depth"], paths["seg"]
    write_dope_json(paths["json"], frame, extra=extra)
    return paths["json"]


def settings_difference(folder: dict[str, Any], run: dict[str, Any], shown: int = 3) -> str:
    """The first ``shown`` settings that differ between a folder's ``_synth_info.json`` and this
    run, as ``key: folder value -> this run's``; a key the folder lacks was added to dope-hope
    after the folder was made."""
    keys = differing_keys(folder, run)

    def value(settings: dict[str, Any], key: str, missing: str) -> str:
        node: Any = settings
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                return missing
            node = node[part]
        return json.dumps(node)

    parts = [f"{key}: {value(folder, key, 'absent (made before this setting existed)')} -> "
             f"{value(run, key, 'absent')}" for key in keys[:shown]]
    more = f"; {len(keys) - shown} more" if len(keys) > shown else ""
    return "; ".join(parts) + more


def check_or_write_info(out_dir: str | os.PathLike, info: dict[str, Any]) -> None:
    """Record the dataset settings; refuse to mix frames made with different settings.

    The first run writes ``_synth_info.json``; later runs (resume, more frames, other shards)
    must have equal settings, else ConfigError names the differing keys with both values
    (:func:`settings_difference`).
    """
    path = Path(out_dir) / INFO_NAME
    text = json.dumps(info, indent=1, sort_keys=True) + "\n"
    if path.is_file():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            old = None
        current = json.loads(text)  # as written: tuples and paths in their JSON form
        if old is not None and old != current:
            raise ConfigError(f"{out_dir}: holds frames generated with other settings "
                              f"({settings_difference(old, current)}); use another --out or "
                              "the same options")
        if old is not None:
            return
    atomic_write_text(path, text)
