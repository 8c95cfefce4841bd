"""Poses on still images: each image read (RGB, its camera, its depth), run through the
predictors, its detection records handed on and its overlay (and belief montages) written:
the loop of `dope-hope infer` on images (streams: :mod:`dope_hope.inference.stream_inference`).

With several images, one whose problem is its own (unreadable, no camera, depth of another
size...) is skipped with a warning and the others still run; ``predictions.jsonl`` always
lists what the overlays show (an interrupted run included).
"""
from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from dope_hope.errors import CameraError, ConfigError, DopeHopeError, InputFileError, OutputPathError
from dope_hope.inference.predictor import DopePredictor, predict_many
from dope_hope.io.camera import ImageCamera, camera_search_description, find_image_camera
from dope_hope.io.images import read_depth_m, read_image_raw, write_rgb
from dope_hope.io.predictions import write_predictions_jsonl
from dope_hope.preprocess import to_rgb8
from dope_hope.viz import belief_montage, overlay_detections


@dataclass(frozen=True)
class ImageOptions:
    """How each image is processed and what is written of it.

    depth: None (no depth), "auto" (each image's annotated depth) or the path of the depth
    image of the single input. depth_scale_mm: millimetres per depth unit (None: the
    annotation's, else 1). depth_calibration: depth multiplied by it. overlay: write
    ``NAME.overlay.png``; belief: write ``NAME.belief.CLASS.png``.
    """

    depth: str | None = None
    depth_scale_mm: float | None = None
    depth_calibration: float = 1.0
    overlay: bool = True
    belief: bool = False


@dataclass
class ImagesResult:
    """records: every detection record; done: images processed; overlays: images whose overlay
    was written; skipped: (image, its error) of each image skipped."""

    records: list[dict] = field(default_factory=list)
    done: int = 0
    overlays: int = 0
    skipped: list[tuple[Path, DopeHopeError]] = field(default_factory=list)


def output_stem(name: str) -> str:
    """A flat file-name stem from a record name (folders joined with '__', suffix dropped)."""
    stem = name.rsplit(".", 1)[0] if "." in Path(name).name else name
    return stem.replace("/", "__").replace("\\", "__")


def check_output_names(images: Sequence[tuple[Path, str]]) -> None:
    """ConfigError when two images would write the same overlay (x.png and x.jpg)."""
    seen: dict[str, str] = {}
    for _, name in images:
        stem = output_stem(name)
        if stem in seen:
            raise ConfigError(f"{seen[stem]} and {name} would write the same {stem}.overlay.png; "
                              "process them in separate runs (or pass --no-overlay)")
        seen[stem] = name


def depth_for(options: ImageOptions, camera: ImageCamera | None) -> tuple[Path | None, float]:
    """(depth path or None, metres per unit) for one image whose camera (with ``depth: auto``,
    its annotation's) is ``camera``."""
    scale_m = None if options.depth_scale_mm is None else options.depth_scale_mm * 0.001
    if options.depth is None:
        return None, 0.001
    if options.depth == "auto":
        path = None if camera is None else camera.depth_path
        recorded = None if camera is None else camera.depth_scale_m
        return path, scale_m if scale_m is not None else (recorded if recorded is not None else 0.001)
    return Path(options.depth), scale_m if scale_m is not None else 0.001


def _resize(rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 -> (hw[0], hw[1], 3); unchanged when already that size."""
    if rgb.shape[:2] == tuple(hw):
        return rgb
    return cv2.resize(rgb, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


def predict_image(predictors: Sequence[DopePredictor], path: Path, name: str, camera: ImageCamera | None,
                  options: ImageOptions, out: Path,
                  warn: Callable[[str], None] = lambda message: None) -> tuple[list[dict], bool]:
    """Detections of one image as records (``image`` = ``name``) and whether an overlay was
    written to ``out``; ``camera``: the one of every image (None: each image's sibling
    annotation's). DopeHopeError for a problem of this image (unreadable, no camera, depth of
    another size...)."""
    raw = read_image_raw(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            rgb = to_rgb8(raw)
        except ValueError as exc:
            raise InputFileError(path, str(exc)) from None
    for w in caught:
        warn(f"{path}: {w.message}")
    H, W = rgb.shape[:2]
    found = find_image_camera(path) if (camera is None or options.depth == "auto") else None
    image_camera = camera or found
    if image_camera is None:
        raise CameraError(f"{path}: no camera intrinsics (looked for {camera_search_description(path)}); "
                          "give --camera K.json or --fx --fy --cx --cy")
    image_camera.check_size(path, W, H)
    depth_path, depth_scale_m = depth_for(options, found if options.depth == "auto" else image_camera)
    depth = None
    if depth_path is not None:
        depth = read_depth_m(depth_path, depth_scale_m)
        if depth.shape != (H, W):
            raise InputFileError(depth_path, f"depth is {depth.shape[1]}x{depth.shape[0]}, "
                                             f"the image {path.name} is {W}x{H}")
    maps = []

    def keep_maps(p, belief, affinity, net_in):
        if options.belief:
            for obj in p.objects:
                maps.append((obj.class_name, net_in.maps_on_image(obj.channels(belief, affinity)[0], p.stride),
                             net_in))

    t0 = time.perf_counter()
    dets = predict_many(predictors, rgb, image_camera.K, depth=depth, calibration=options.depth_calibration,
                        on_maps=keep_maps)
    elapsed = time.perf_counter() - t0
    records = [d.to_json(name, time=round(elapsed, 4)) for d in dets]
    out_stem = output_stem(name)
    if options.overlay:
        write_rgb(out / f"{out_stem}.overlay.png", overlay_detections(rgb, dets, image_camera.K))
    for class_name, m, net_in in maps:
        write_rgb(out / f"{out_stem}.belief.{class_name}.png",
                  belief_montage(m, _resize(rgb, net_in.resized_hw)))
    return records, options.overlay


def predict_images(images: Sequence[tuple[Path, str]], predictors: Sequence[DopePredictor], out: Path,
                   camera: ImageCamera | None = None, options: ImageOptions = ImageOptions(), *,
                   progress: bool = True, on_record: Callable[[dict], None] = lambda record: None,
                   warn: Callable[[str], None] = lambda message: None) -> ImagesResult:
    """:func:`predict_image` on each (path, record name) of ``images``, then
    ``out/predictions.jsonl`` (atomically; also when interrupted, with what was processed).

    A single image's error is raised; with several, an image's own error (not an output
    path's) skips it: ``warn`` is told and the result lists it. ``on_record`` gets each
    record as its image is done; ``progress``: a bar on stderr for two or more images.
    """
    result = ImagesResult()
    bar = tqdm(images, desc="infer", unit="img", disable=not progress or len(images) < 2, file=sys.stderr)
    try:
        for path, name in bar:
            try:
                recs, wrote = predict_image(predictors, path, name, camera, options, out, warn)
            except OutputPathError:
                raise
            except DopeHopeError as exc:  # this image's problem: the others still run
                if len(images) == 1:
                    raise
                result.skipped.append((path, exc))
                bar.clear()
                warn(f"{exc}; image skipped")
                continue
            for rec in recs:
                on_record(rec)
            result.records += recs
            result.done += 1
            result.overlays += wrote
    finally:
        bar.close()
        # predictions.jsonl always lists what the overlays show (interrupted runs included)
        if result.done:
            write_predictions_jsonl(out / "predictions.jsonl", result.records)
    return result
