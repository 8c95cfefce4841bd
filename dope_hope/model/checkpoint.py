"""Checkpoints: save (atomic), load (weights_only), build the model, import official DOPE weights.

A checkpoint is a plain dict that ``torch.load(..., weights_only=True)`` can read (tensors,
numbers, strings, lists, tuples, dicts; no pickled classes)::

    format            "dope-hope-checkpoint"; format_version 1
    model             state dict (CPU tensors)
    config            the full config that built the model (model/input/targets/train/...)
    objects           [{class_name, size_m: [x, y, z] cuboid extents in the MESH frame (m),
                       frame: "mesh" | "legacy" (the object frame the network's keypoints use),
                       symmetries: BOP models_info symmetry fields (mm) or None,
                       min_score: the object's own score threshold, optional}], one per
                      belief/affinity group, in channel order (``model.num_objects`` of them)
    min_score         the model's own score threshold, optional
    object            objects[0], written for one-object models only (what older readers
                      read; a checkpoint with ``object`` alone is a one-object model)
    keypoint_order    "dope-current" (geometry.KEYPOINT_ORDER) or "dope-legacy"
    normalization     {mean: [3], std: [3]} applied to RGB in [0, 1]
    optimizer, scheduler   state dicts or None
    step, epoch       ints (resume point: the next epoch is ``epoch + 1``)
    rng               {python, numpy, torch, cuda} generator states for an exact resume
    source            where the weights came from (e.g. an imported official file) or None
    extra             free-form plain data or None
"""
from __future__ import annotations

import os
import pickle
import random
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dope_hope.catalog import get_object
from dope_hope.config import load_config
from dope_hope.errors import ConfigError, InputFileError, ModelFileError
from dope_hope.geometry import KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER
from dope_hope.io.atomic import atomic_write_stream
from dope_hope.io.paths import require_file, weights_format
from dope_hope.model.info import OBJECT_FRAMES, ModelInfo
from dope_hope.model.network import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    DopeNetwork,
    build_model,
    num_objects_of,
)
from dope_hope.version import __version__

CHECKPOINT_FORMAT = "dope-hope-checkpoint"
FORMAT_VERSION = 1
_REQUIRED = ("model", "config", "keypoint_order", "normalization")

#: What the official DOPE inference code feeds the network (NVlabs/Deep_Object_Pose
#: ``common/detector.py`` and ``scripts/train2/inference/detector.py``: torchvision
#: ``Normalize((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))``; the 2018 ROS1 node used
#: mean = std = 0.5 instead, for the original YCB weights).
OFFICIAL_NORMALIZATION = {
    "mean": list(IMAGENET_MEAN),
    "std": list(IMAGENET_STD),
    "source": "NVlabs/Deep_Object_Pose common/detector.py (ImageNet mean/std)",
}


# ----------------------------------------------------------------------------- helpers
def unwrap_model(model: nn.Module) -> nn.Module:
    """The plain module inside DistributedDataParallel/DataParallel/torch.compile wrappers."""
    while True:
        if isinstance(model, (nn.parallel.DistributedDataParallel, nn.DataParallel)):
            model = model.module
        elif hasattr(model, "_orig_mod"):
            model = model._orig_mod
        else:
            return model


def strip_prefix(state: dict[str, Any], prefix: str = "module.") -> dict[str, Any]:
    """Remove ``prefix`` from every key that has it (DataParallel/DDP saves)."""
    return {k[len(prefix):] if k.startswith(prefix) else k: v for k, v in state.items()}


def _weights_only_value(obj: Any) -> Any:
    """Convert numpy values / paths to types ``weights_only`` loading accepts."""
    if isinstance(obj, dict):
        return {(_weights_only_value(k) if not isinstance(k, str) else k): _weights_only_value(v)
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        seq = [_weights_only_value(v) for v in obj]
        return tuple(seq) if isinstance(obj, tuple) else seq
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _summarize(keys: list[str], limit: int = 3) -> str:
    shown = ", ".join(keys[:limit])
    return f"{shown}, ... ({len(keys)} in all)" if len(keys) > limit else shown


def check_state_dict(expected: dict[str, torch.Tensor], state: dict[str, Any],
                     path: str | os.PathLike, ignore_missing_prefix: str | None = None) -> None:
    """Raise ModelFileError (one line, naming the file) unless ``state`` fits ``expected``.

    ``expected`` may hold meta tensors (only names and shapes are compared). Missing keys
    starting with ``ignore_missing_prefix`` are allowed.
    """
    unexpected = [k for k in state if k not in expected]
    missing = [k for k in expected if k not in state
               and not (ignore_missing_prefix and k.startswith(ignore_missing_prefix))]
    if unexpected:
        raise ModelFileError(path, f"unexpected keys {_summarize(unexpected)}: weights for another architecture")
    if missing:
        raise ModelFileError(path, f"missing keys {_summarize(missing)}: weights for another architecture")
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise ModelFileError(path, f"{key} is not a tensor")
        if tuple(value.shape) != tuple(expected[key].shape):
            raise ModelFileError(path, f"{key} has shape {tuple(value.shape)}, the model expects "
                                       f"{tuple(expected[key].shape)}: weights for another architecture")


def expected_state(config: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Names and shapes of the state dict ``config`` builds (meta tensors: no memory, fast)."""
    with torch.device("meta"):
        model = build_model(config, load_backbone=False)
    return model.state_dict()


def _torch_load(path: Path) -> Any:
    """torch.load with weights_only=True; every failure becomes a one-line ModelFileError."""
    try:
        require_file(path)
    except InputFileError as exc:
        raise ModelFileError(path, exc.problem) from None
    kind = weights_format(path)
    if kind == "empty":
        raise ModelFileError(path, "empty file, not a torch weights file")
    if kind == "other":
        raise ModelFileError(path, "not a torch weights file (neither the zip archive nor the pickle "
                                   "stream torch.save writes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if "weights only" in str(exc).lower():
            raise ModelFileError(path, "refused: it pickles Python objects other than weights "
                                       "(loaded with weights_only=True); not a checkpoint") from None
        raise ModelFileError(path, "not a torch weights file (unpickling failed)") from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, EOFError) or "zip archive" in text or "central directory" in text:
            raise ModelFileError(path, "truncated or not a torch weights file") from None
        raise ModelFileError(path, f"unreadable weights file ({text[:120]})") from None
    except Exception as exc:  # noqa: BLE001 - the weights-only unpickler raises KeyError etc. on junk
        raise ModelFileError(path, f"not a torch weights file ({type(exc).__name__} while unpickling)") from None


# ----------------------------------------------------------------------------- rng state
def rng_state() -> dict[str, Any]:
    """Python, numpy (global) and torch generator states, weights_only-loadable."""
    np_state = np.random.get_state(legacy=False)
    np_state["state"] = dict(np_state["state"], key=np_state["state"]["key"].astype(np.int64))
    state = {
        "python": random.getstate(),
        "numpy": _weights_only_value(np_state),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`rng_state` (CUDA states only where CUDA is available)."""
    if state.get("python") is not None:
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))
    if state.get("numpy") is not None:
        np_state = dict(state["numpy"])
        inner = dict(np_state["state"])
        inner["key"] = np.asarray(inner["key"].numpy() if isinstance(inner["key"], torch.Tensor)
                                  else inner["key"], dtype=np.uint32)
        np_state["state"] = inner
        np.random.set_state(np_state)
    if state.get("torch") is not None:
        torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ----------------------------------------------------------------------------- save / load
def make_object_info(class_name: str, size_m: Any = None, frame: str = "mesh",
                     symmetries: dict[str, Any] | None = None) -> dict[str, Any]:
    """``{class_name, size_m (mesh frame, m), frame}`` (plus ``symmetries``, the BOP fields in
    mm, when given); size defaults to the catalog's."""
    if frame not in OBJECT_FRAMES:
        raise ConfigError(f"object frame must be one of {OBJECT_FRAMES}, got {frame!r}")
    if size_m is None:
        size_m = get_object(class_name).size_array
    size = [float(v) for v in np.asarray(size_m, dtype=np.float64).reshape(-1)]
    if len(size) != 3 or min(size) <= 0:
        raise ConfigError(f"object size must be 3 positive extents in metres, got {size}")
    info = {"class_name": str(class_name), "size_m": size, "frame": frame}
    if symmetries is not None:
        info["symmetries"] = _weights_only_value(dict(symmetries))
    return info


def object_entries(object_info: dict[str, Any] | list[dict[str, Any]] | tuple) -> list[dict[str, Any]]:
    """The checkpoint's ``objects`` list from one object dict or a list of them (channel
    order), each through :func:`make_object_info`; ConfigError for an empty list, mixed
    frames or a repeated class (case-insensitive)."""
    items = [object_info] if isinstance(object_info, dict) else list(object_info)
    if not items:
        raise ConfigError("a model needs at least one object")
    out = [make_object_info(o["class_name"], o.get("size_m"), o.get("frame", "mesh"), o.get("symmetries"))
           for o in items]
    if len({o["frame"] for o in out}) != 1:
        raise ConfigError("the objects of one model must share one frame")
    names = [o["class_name"].lower() for o in out]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ConfigError(f"object class {repeated[0]!r} is listed twice (class names are case-insensitive)")
    return out


@dataclass
class TrainingState:
    """Where a training run stands, what a checkpoint keeps for ``--resume``.

    optimizer, scheduler: their state dicts are written (None: none). step, epoch: the
    counters (the next epoch is ``epoch + 1``). extra: free-form plain data (the trainer's
    bookkeeping) or None.
    """

    optimizer: torch.optim.Optimizer | None = None
    scheduler: Any = None
    step: int = 0
    epoch: int = 0
    extra: dict[str, Any] | None = None


def save_checkpoint(
    path: str | os.PathLike,
    model: nn.Module,
    config: dict[str, Any],
    object_info: dict[str, Any] | list[dict[str, Any]],
    training: TrainingState | None = None,
    *,
    keypoint_order: str | None = None,
    normalization: dict[str, Any] | None = None,
    source: str | None = None,
) -> Path:
    """Write a checkpoint atomically (a crash leaves the old file or none, never half a file).

    Args:
        model: the network (DDP/compile wrappers are unwrapped; tensors saved on CPU).
        config: the full config that built it.
        object_info: ``{class_name, size_m, frame[, symmetries]}`` (see :func:`make_object_info`),
            or a list of them in channel-group order, one per ``model.num_objects``.
        training: the run's :class:`TrainingState` (None: no optimizer, step and epoch 0).
        keypoint_order: default "dope-legacy" for frame "legacy", else "dope-current".
        normalization: default ImageNet mean/std.
    Returns the path written.
    """
    path = Path(path)
    run = training or TrainingState()
    objects = object_entries(object_info)
    if len(objects) != num_objects_of(config):
        raise ConfigError(f"{len(objects)} object(s) given for a model of model.num_objects = "
                          f"{num_objects_of(config)}")
    info = objects[0]
    if keypoint_order is None:
        keypoint_order = LEGACY_KEYPOINT_ORDER if info["frame"] == "legacy" else KEYPOINT_ORDER
    norm = normalization or {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}
    state = {k: v.detach().cpu() for k, v in unwrap_model(model).state_dict().items()}
    ckpt = {
        "format": CHECKPOINT_FORMAT,
        "format_version": FORMAT_VERSION,
        "dope_hope_version": __version__,
        "model": state,
        "config": _weights_only_value(config),
        "objects": objects,
        **({"object": info} if len(objects) == 1 else {}),
        "keypoint_order": keypoint_order,
        "normalization": _weights_only_value(norm),
        "optimizer": run.optimizer.state_dict() if run.optimizer is not None else None,
        "scheduler": run.scheduler.state_dict() if run.scheduler is not None else None,
        "step": int(run.step),
        "epoch": int(run.epoch),
        "rng": rng_state(),
        "source": source,
        "extra": _weights_only_value(run.extra) if run.extra is not None else None,
    }
    atomic_write_stream(path, lambda f: torch.save(ckpt, f))
    return path


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read and validate a checkpoint (``weights_only=True``, tensors on CPU).

    Raises ModelFileError naming the file for: a missing, truncated or non-torch file; a file
    that pickles arbitrary objects; a bare state dict or other non-checkpoint; weights that
    do not fit the architecture its own config describes.
    """
    path = Path(path)
    ckpt = _torch_load(path)
    if not isinstance(ckpt, dict):
        raise ModelFileError(path, f"not a dope-hope checkpoint (holds a {type(ckpt).__name__})")
    if ckpt.get("format") != CHECKPOINT_FORMAT:
        if ckpt and all(isinstance(v, torch.Tensor) for v in ckpt.values()):
            raise ModelFileError(path, "a bare state dict, not a dope-hope checkpoint "
                                       "(official DOPE weights: use import-official)")
        raise ModelFileError(path, "not a dope-hope checkpoint (no 'format' marker)")
    if int(ckpt.get("format_version", 0)) > FORMAT_VERSION:
        raise ModelFileError(path, f"checkpoint format {ckpt.get('format_version')} is newer than "
                                   f"this dope-hope understands ({FORMAT_VERSION})")
    missing = [k for k in _REQUIRED if k not in ckpt]
    if missing:
        raise ModelFileError(path, f"checkpoint lacks {', '.join(missing)}")
    if not isinstance(ckpt["model"], dict) or not isinstance(ckpt["config"], dict):
        raise ModelFileError(path, "checkpoint 'model' and 'config' must be dicts")
    if "objects" not in ckpt and "object" not in ckpt:
        raise ModelFileError(path, "checkpoint lacks objects")
    entries = ckpt["objects"] if "objects" in ckpt else [ckpt["object"]]
    if not isinstance(entries, (list, tuple)) or not entries or not all(
            isinstance(o, dict) and "class_name" in o and o.get("frame") in OBJECT_FRAMES for o in entries):
        key = "objects" if "objects" in ckpt else "object"
        raise ModelFileError(path, f"checkpoint '{key}' must hold class_name, size_m and frame"
                                   + (" per object" if key == "objects" else ""))
    info = ModelInfo.from_checkpoint(ckpt, path)
    if info.num_objects != num_objects_of(ckpt["config"]):
        raise ModelFileError(path, f"checkpoint lists {info.num_objects} object(s) but its config "
                                   f"builds model.num_objects = {num_objects_of(ckpt['config'])}")
    try:
        expected = expected_state(ckpt["config"])
    except ConfigError as exc:
        raise ModelFileError(path, f"its config is invalid ({exc})") from None
    check_state_dict(expected, ckpt["model"], path)
    bad = [k for k, v in ckpt["model"].items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        warnings.warn(f"{path}: {len(bad)} of {len(ckpt['model'])} weight tensors hold NaN or infinity "
                      f"({_summarize(bad)}): its outputs are meaningless (a diverged training run?)",
                      RuntimeWarning, stacklevel=2)
    return ckpt


#: ``source`` of a checkpoint that is a start for training, not a detector (the shipped
#: pretrained lite start): inference and export refuse it.
PRETRAINED_START_SOURCE = "pretrained start"


def save_inference_checkpoint(src: str | os.PathLike, dst: str | os.PathLike,
                              source: str | None = None, min_score: float | None = None,
                              object_min_scores: Mapping[str, float] | None = None) -> Path:
    """Copy a checkpoint without its training state (optimizer, scheduler, RNG): what a
    model ships as. Adam's moments double a checkpoint's size and are useless for inference;
    ``--resume`` needs the full file. ``source`` replaces the recorded origin (e.g.
    :data:`PRETRAINED_START_SOURCE`). ``min_score`` and ``object_min_scores``: as
    :func:`with_min_scores`. Written atomically; returns ``dst``."""
    ckpt = load_checkpoint(src)
    ckpt.update(optimizer=None, scheduler=None, rng=None)
    if source is not None:
        ckpt["source"] = source
    atomic_write_stream(dst, lambda f: torch.save(with_min_scores(ckpt, src, min_score, object_min_scores), f))
    return Path(dst)


def record_min_scores(path: str | os.PathLike, object_min_scores: Mapping[str, float]) -> Path:
    """Record each object's own score threshold in the checkpoint ``path`` itself, training
    state and all (:func:`with_min_scores`); rewritten atomically; returns ``path``."""
    ckpt = with_min_scores(load_checkpoint(path), path, None, object_min_scores)
    atomic_write_stream(path, lambda f: torch.save(ckpt, f))
    return Path(path)


def with_min_scores(ckpt: dict[str, Any], where: str | os.PathLike, min_score: float | None = None,
                    object_min_scores: Mapping[str, float] | None = None) -> dict[str, Any]:
    """``ckpt`` (read from ``where``) with ``min_score``, the model's own default score
    threshold (:attr:`ModelInfo.min_score <dope_hope.model.info.ModelInfo.min_score>`; kept
    when None), and ``object_min_scores`` {class name: threshold}, each object's own
    (:attr:`ObjectInfo.min_score <dope_hope.model.info.ObjectInfo.min_score>`), set in place
    and checked (ConfigError for a class the model does not hold or a bad value)."""
    if min_score is not None:
        ckpt["min_score"] = min_score
    if object_min_scores:
        entries = ckpt.get("objects") or [ckpt.get("object") or {}]
        names = [e.get("class_name") for e in entries]
        for name, value in object_min_scores.items():
            if name not in names:
                raise ConfigError(f"{name!r} is not an object of {where} ({', '.join(map(str, names))})")
            entries[names.index(name)]["min_score"] = float(value)
        ckpt["objects"] = entries
        if len(entries) == 1:
            ckpt["object"] = entries[0]
    if min_score is not None or object_min_scores:
        ModelInfo.from_checkpoint(ckpt, where)
    return ckpt


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[DopeNetwork, dict[str, Any]]:
    """Load a checkpoint and build its network: ``(model in eval mode on device, checkpoint)``.

    Raises ModelFileError for a pretrained start (:data:`PRETRAINED_START_SOURCE`): it finds
    cuboid keypoints of many objects and knows no object's size, so its poses would be wrong.
    """
    ckpt = load_checkpoint(path)
    if ckpt.get("source") == PRETRAINED_START_SOURCE:
        raise ModelFileError(path, "a pretrained start, not a detector of one object: train your "
                                   "object(s) from it (`dope-hope train --config lite`, its default start)")
    model = build_model(ckpt["config"], load_backbone=False)
    model.load_state_dict(ckpt["model"], strict=True)
    return model.to(device).eval(), ckpt


# ----------------------------------------------------------------------------- official weights
def official_object_name(stem: str) -> str | None:
    """The object an official weights file's name gives: ``Ketchup`` (the HOPE weights),
    ``net_Ketchup_0060`` / ``final_net_Ketchup_0060`` (the training script's
    ``net_{namefile}_{epoch}``), ``cracker_60`` (the original YCB weights); None for the
    training script's default ``net_epoch_0060`` or an empty name."""
    name = re.sub(r"^(final_)?net_", "", stem)
    name = re.sub(r"_\d+$", "", name)
    return None if not name or name.lower() == "epoch" else name


def import_official(
    pth_path: str | os.PathLike,
    class_name: str,
    out_path: str | os.PathLike | None = None,
    size_m: Any = None,
    frame: str = "legacy",
) -> dict[str, Any]:
    """Wrap an official DOPE ``.pth`` (bare state dict, maybe ``module.``-prefixed) as a checkpoint.

    The weights must fit the DOPE-DR-50 layout exactly. Records ImageNet normalization (what
    the official inference code uses), the cuboid size in the mesh frame (the catalog's
    unless ``size_m`` is given) and the object frame: "legacy" with keypoint order
    "dope-legacy" (the official HOPE weights' frame and that of weights trained on NViSII
    data; ARCHITECTURE.md), or "mesh" with "dope-current" when the object frame is the
    official cuboid frame itself (``size_m`` = the official config's ``dimensions``).
    Writes it if ``out_path``.
    """
    if frame not in OBJECT_FRAMES:
        raise ConfigError(f"object frame must be one of {', '.join(OBJECT_FRAMES)}, got {frame!r}")
    pth_path = Path(pth_path)
    state = _torch_load(pth_path)
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not state:
        raise ModelFileError(pth_path, "expected a DOPE state dict")
    if state.get("format") == CHECKPOINT_FORMAT:
        raise ModelFileError(pth_path, "already a dope-hope checkpoint; nothing to import")
    state = strip_prefix(state, "module.")
    config = load_config("dope_dr_50")
    expected = expected_state(config)
    check_state_dict(expected, state, pth_path)
    info = make_object_info(class_name, size_m, frame=frame)
    source = f"official DOPE weights {pth_path.name}"
    ckpt = {
        "format": CHECKPOINT_FORMAT,
        "format_version": FORMAT_VERSION,
        "dope_hope_version": __version__,
        "model": {k: state[k].detach().to("cpu", torch.float32) for k in expected},
        "config": config,
        "objects": [info],
        "object": info,
        "keypoint_order": LEGACY_KEYPOINT_ORDER if frame == "legacy" else KEYPOINT_ORDER,
        "normalization": dict(OFFICIAL_NORMALIZATION),
        "optimizer": None,
        "scheduler": None,
        "step": 0,
        "epoch": 0,
        "rng": None,
        "source": source,
        "extra": None,
    }
    if out_path is not None:
        atomic_write_stream(out_path, lambda f: torch.save(ckpt, f))
    return ckpt
