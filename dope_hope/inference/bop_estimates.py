"""Pose estimates of a BOP test split: the models by BOP obj_id, run on the targeted images
(the library side of `dope-hope bop-submit`; the CSV is written by :mod:`dope_hope.io.bop_csv`).

A model's objects are the BOP obj_ids of its classes (the HOPE catalog's, or a class named
``obj_NNNNNN``); a multi-object model covers all of its objects with one forward pass; models
of one object and of several mix, but no object may have two models.
"""
from __future__ import annotations

import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
from dope_hope.inference import backends  # looked up at each call: a substituted open_backend counts
from dope_hope.inference.options import preset_options
from dope_hope.inference.predictor import DopePredictor, predict_many
from dope_hope.io.bop_csv import BopEstimate
from dope_hope.io.images import read_depth_m, read_rgb
from dope_hope.io.models_dir import bop_obj_id, find_object_mesh


def obj_id_of(class_name: str) -> int:
    """BOP obj_id of a model's class (:func:`dope_hope.io.models_dir.bop_obj_id`).

    Raises:
        UnknownObjectError: the class has none.
    """
    obj_id = bop_obj_id(class_name)
    if obj_id is None:
        raise UnknownObjectError(f"model class {class_name!r} has no BOP obj_id (not a HOPE object, "
                                 "not named obj_NNNNNN)")
    return obj_id


@dataclass
class BopModels:
    """predictors: obj_id -> the predictor of the model detecting it (a multi-object model's
    predictor appears under each of its ids); class_of: obj_id -> class name."""

    predictors: dict[int, Any] = field(default_factory=dict)
    class_of: dict[int, str] = field(default_factory=dict)


def load_bop_models(weights: Sequence[str | os.PathLike], models_dir: Path | None, models_dir_given: bool,
                    predictor_options: Mapping[str, Any], backend: str = "auto", device: str = "cpu",
                    threads: int | None = None, preset: str = "fast") -> BopModels:
    """Open every model and give it its objects' meshes for the depth steps.

    Args:
        weights: checkpoints / ONNX files, of one object or several each.
        models_dir: BOP models folder (obj_NNNNNN.ply, mm) or None (each model's cuboid).
        models_dir_given: the folder was named by the user: it must hold every object's mesh
            (a dataset's own ``models/`` may lack one: that object keeps its cuboid).
        predictor_options: DopePredictor overrides (``height``, ``min_score``, ``icp``, ...).
        preset: the options they are read over (:func:`~dope_hope.inference.options.preset_options`).

    Raises:
        ConfigError: two models (or one model twice) for the same obj_id.
    """
    out = BopModels()
    for w in weights:
        opened = backends.open_backend(w, backend, device, threads)
        names = [o.class_name for o in backends.backend_objects(opened)]
        ids = [obj_id_of(name) for name in names]
        for obj_id, name in zip(ids, names):
            if obj_id in out.predictors or ids.count(obj_id) > 1:
                raise ConfigError(f"{w}: a second model for obj_id {obj_id} ({name})")
        meshes = {name: find_object_mesh(name, models_dir, required=models_dir_given) for name in names}
        fixed = getattr(opened, "fixed_input_hw", None) is not None
        found = {k: v for k, v in meshes.items() if v is not None}
        predictor = DopePredictor(opened, mesh=found,
                                  options=preset_options(preset, predictor_options, fixed_size=fixed, meshes=bool(found)))
        for obj_id, name in zip(ids, names):
            out.predictors[obj_id], out.class_of[obj_id] = predictor, name
    return out


@dataclass
class BopRun:
    """estimates: every pose; images: the images processed; seconds: their total time
    (reading + every model)."""

    estimates: list[BopEstimate]
    images: int
    seconds: float


def estimate_frames(split_dir: Path, frames: Sequence[Any], wanted: Mapping[tuple[int, int], Any] | None,
                    models: BopModels, use_depth: bool = True, depth_calibration: float = 1.0,
                    progress: bool = False) -> BopRun:
    """Run each image's targeted objects' models (``wanted``: (scene_id, im_id) -> obj_ids, or
    None: every model on every image) on the frames of :func:`dope_hope.io.bop.targeted_frames`,
    decoding only the targeted objects; each estimate carries its image's total time.

    Raises:
        InputFileError: a targeted image without its file.
    """
    estimates: list[BopEstimate] = []
    seconds, images = 0.0, 0
    for bf in tqdm(frames, desc="bop-submit", unit="img", disable=not progress, file=sys.stderr):
        frame = bf.annotation
        objs = sorted(models.predictors) if wanted is None else \
            sorted(set(wanted[(bf.scene_id, bf.im_id)]) & set(models.predictors))
        if not objs:
            continue
        if frame.image_path is None:
            raise InputFileError(Path(split_dir) / f"{bf.scene_id:06d}", f"no image for im_id {bf.im_id}")
        t0 = time.perf_counter()
        rgb = read_rgb(frame.image_path)
        depth = None
        if use_depth and frame.depth_path is not None:
            depth = read_depth_m(frame.depth_path, frame.depth_scale_m)
        predictors = list({id(models.predictors[o]): models.predictors[o] for o in objs}.values())
        dets = predict_many(predictors, rgb, frame.K, depth=depth, calibration=depth_calibration,
                            classes={models.class_of[o] for o in objs})
        elapsed = time.perf_counter() - t0
        seconds += elapsed
        images += 1
        by_class = {models.class_of[o]: o for o in objs}
        estimates += [BopEstimate(bf.scene_id, bf.im_id, by_class[d.class_name], float(d.score), d.R, d.t,
                                  round(elapsed, 4)) for d in dets]
    return BopRun(estimates, images, seconds)
