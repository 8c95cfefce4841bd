"""What inference needs to know about a model, validated once whatever file it came from.

A dope-hope checkpoint (``objects`` / ``object``, ``keypoint_order``, ``normalization``,
``config.input``) and a dope-hope ONNX file (``metadata_props``, :class:`dope_hope.model.
onnx_contract.OnnxModelInfo`, a subclass) both become a :class:`ModelInfo`;
:meth:`ModelInfo.validate` is the one check of those fields (torch backend, ONNX backend and
export all go through it). A model detects one or more objects (:class:`ObjectInfo`, in
channel-group order: object k owns belief channels [9k, 9k + 9) and affinity channels
[16k, 16k + 16)). No torch import here.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError, DopeHopeError, ModelFileError
from dope_hope.geometry import KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER
from dope_hope.io.bop import parse_symmetries
from dope_hope.io.jsonfields import JsonFields
from dope_hope.model.settings import InputSettings

#: Object frames a model may be trained in (see docs/ARCHITECTURE.md, "legacy frame").
OBJECT_FRAMES = ("mesh", "legacy")
#: Channels of one object's group: belief maps, affinity fields.
GROUP_BELIEF, GROUP_AFFINITY = 9, 16


def group_channels(k: int, num_objects: int) -> np.ndarray:
    """(25,) int: object ``k``'s channels within cat(belief (9N), affinity (16N)) of a model
    of ``num_objects`` objects: its 9 belief maps, then its 16 affinity fields."""
    belief = np.arange(GROUP_BELIEF * k, GROUP_BELIEF * (k + 1))
    affinity = GROUP_BELIEF * num_objects + np.arange(GROUP_AFFINITY * k, GROUP_AFFINITY * (k + 1))
    return np.concatenate([belief, affinity])


@dataclass(frozen=True)
class ObjectInfo:
    """One object of a model.

    class_name: its class. size_m: (3,) cuboid extents, mesh frame, metres. symmetries: the
    BOP ``models_info`` symmetry fields (``symmetries_discrete`` / ``symmetries_continuous``,
    BOP units: mm) as a dict, or None when none are declared. min_score: this object's own
    pose-score threshold (chosen on labelled frames, :mod:`dope_hope.evaluation.thresholds`),
    or None: the model's (:attr:`ModelInfo.min_score`), else the inference options' default;
    an explicit ``min_score`` still wins.
    """

    class_name: str
    size_m: tuple[float, float, float]
    symmetries: Mapping[str, Any] | None = None
    min_score: float | None = None

    def to_dict(self, frame: str) -> dict[str, Any]:
        """The checkpoint / ONNX metadata entry ``{class_name, size_m, frame, symmetries}``
        (and ``min_score`` when the object has its own)."""
        entry = {"class_name": self.class_name, "size_m": [float(v) for v in self.size_m], "frame": frame,
                 "symmetries": None if self.symmetries is None else dict(self.symmetries)}
        if self.min_score is not None:
            entry["min_score"] = float(self.min_score)
        return entry


def score_threshold_problem(value: Any) -> str | None:
    """Why ``value`` is no score threshold (a finite number >= 0, or None), or None."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        return f"must be a finite number >= 0 or null, got {value!r}"
    return None


def object_from_dict(entry: Any, path: str | os.PathLike, where: str) -> tuple[ObjectInfo, str]:
    """(ObjectInfo, frame) of one ``{class_name, size_m, frame, symmetries[, min_score]}`` entry
    (frame "mesh" when absent); ModelFileError naming ``where`` for a malformed entry."""
    if not isinstance(entry, Mapping) or not isinstance(entry.get("class_name"), str) or not entry["class_name"]:
        raise ModelFileError(path, f"model metadata: {where} must hold a class_name")
    try:
        size = tuple(float(v) for v in np.asarray(entry.get("size_m"), dtype=np.float64).reshape(3))
    except (TypeError, ValueError):
        raise ModelFileError(path, f"model metadata: {where}.size_m must hold 3 extents in metres") from None
    sym = entry.get("symmetries")
    min_score = entry.get("min_score")
    if problem := score_threshold_problem(min_score):
        raise ModelFileError(path, f"model metadata: {where}.min_score {problem}")
    return ObjectInfo(str(entry["class_name"]), size, None if sym is None else dict(sym),
                      None if min_score is None else float(min_score)), str(entry.get("frame", "mesh"))


@dataclass
class ModelInfo:
    """Model metadata.

    class_name: object the model detects (the first object of a multi-object model). size_m:
    (3,) its cuboid extents, mesh frame, metres. objects: every object, in channel-group
    order (default: the one object ``class_name``/``size_m``, no symmetries).
    frame: "mesh" | "legacy". keypoint_order: "dope-current" | "dope-legacy" (must match frame).
    mean, std: the model's normalization of RGB in [0, 1]. input_hw: (H, W) training input
    size, or None when unknown. min_score: the model's own default pose-score threshold
    (chosen for it and recorded with its weights; None: the inference options' default);
    an explicit ``min_score`` still wins (:meth:`~dope_hope.inference.options.
    InferenceOptions.from_mapping`).
    """

    class_name: str
    size_m: tuple[float, float, float]
    frame: str
    keypoint_order: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    input_hw: tuple[int, int] | None
    min_score: float | None = field(default=None, kw_only=True)
    objects: tuple[ObjectInfo, ...] = field(default=(), kw_only=True)

    def __post_init__(self) -> None:
        if not self.objects:
            self.objects = (ObjectInfo(str(self.class_name), tuple(self.size_m)),)
        self.objects = tuple(self.objects)

    @property
    def legacy(self) -> bool:
        return self.frame == "legacy"

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(o.class_name for o in self.objects)

    def object_index(self, class_name: str) -> int:
        """Channel group of ``class_name`` (exact name first, then case-insensitive); KeyError."""
        names = self.class_names
        if class_name in names:
            return names.index(class_name)
        lower = [n.lower() for n in names]
        if lower.count(class_name.lower()) == 1:
            return lower.index(class_name.lower())
        raise KeyError(class_name)

    def validate(self, path: str | os.PathLike) -> None:
        """Raise ModelFileError (one line, naming ``path``) for an inconsistent value."""
        def bad(problem: str):
            raise ModelFileError(path, f"model metadata: {problem}")

        for name in ("size_m", "mean", "std"):
            v = getattr(self, name)
            if v is None or len(v) != 3 or not np.all(np.isfinite(np.asarray(v, dtype=np.float64))):
                bad(f"{name} must hold 3 finite numbers, got {v}")
        if min(self.size_m) <= 0:
            bad(f"cuboid size {list(self.size_m)} is not positive")
        if min(self.std) <= 0:
            bad(f"std {list(self.std)} must be positive")
        expected = LEGACY_KEYPOINT_ORDER if self.frame == "legacy" else KEYPOINT_ORDER
        if self.frame not in OBJECT_FRAMES or self.keypoint_order != expected:
            bad(f"frame {self.frame!r} with keypoint order {self.keypoint_order!r} is not supported "
                f"(expected {expected!r})")
        if self.input_hw is not None and (len(self.input_hw) != 2 or min(self.input_hw) < 1):
            bad(f"input_hw must be [H, W] or null, got {self.input_hw}")
        if problem := score_threshold_problem(self.min_score):
            bad(f"min_score {problem}")
        self._validate_objects(path, bad)

    def _validate_objects(self, path: str | os.PathLike, bad) -> None:
        first = self.objects[0]
        if first.class_name != self.class_name or tuple(first.size_m) != tuple(self.size_m):
            bad(f"class_name {self.class_name!r} / size_m {list(self.size_m)} differ from the first "
                f"object's ({first.class_name!r}, {list(first.size_m)})")
        seen: set[str] = set()
        for k, obj in enumerate(self.objects):
            size = np.asarray(obj.size_m, dtype=np.float64)
            if size.shape != (3,) or not np.all(np.isfinite(size)) or size.min() <= 0:
                bad(f"objects[{k}] ({obj.class_name}) cuboid size {list(obj.size_m)} is not 3 positive extents")
            if not obj.class_name or obj.class_name.lower() in seen:
                bad(f"objects[{k}]: class name {obj.class_name!r} is empty or repeated (case-insensitive)")
            seen.add(obj.class_name.lower())
            if problem := score_threshold_problem(obj.min_score):
                bad(f"objects[{k}] ({obj.class_name}) min_score {problem}")
            if obj.symmetries is not None:
                try:
                    parse_symmetries(JsonFields(path), dict(obj.symmetries), f"objects[{k}].symmetries")
                except DopeHopeError as exc:
                    bad(str(getattr(exc, "problem", exc)))

    @classmethod
    def from_checkpoint(cls, ckpt: dict[str, Any], path: str | os.PathLike = "<checkpoint>") -> ModelInfo:
        """The validated info of a checkpoint dict; ModelFileError for missing or bad fields.

        ``objects`` (list of ``{class_name, size_m, frame, symmetries}``) when present, else
        the single ``object`` of older checkpoints."""
        entries = ckpt.get("objects")
        if entries is None:
            obj = ckpt.get("object") or {}
            try:
                np.asarray(obj.get("size_m"), dtype=np.float64).reshape(3)
            except (TypeError, ValueError):
                raise ModelFileError(path, "checkpoint 'object.size_m' must hold 3 extents in metres") from None
            entries, where = [obj], "object"
        elif not isinstance(entries, (list, tuple)) or not entries:
            raise ModelFileError(path, "checkpoint 'objects' must be a non-empty list")
        else:
            where = "objects"
        objects, frames = objects_from_entries(entries, path, where)
        norm = ckpt.get("normalization") or {}
        try:
            mean = tuple(float(v) for v in norm["mean"])
            std = tuple(float(v) for v in norm["std"])
        except (KeyError, TypeError, ValueError):
            raise ModelFileError(path, "checkpoint 'normalization' must hold mean and std") from None
        recipe = ckpt.get("config") or {}
        input_hw: tuple[int, int] | None = None
        if "input" in recipe or "train" in recipe:  # a recipe leaves out what keeps its default
            try:
                input_hw = InputSettings.from_mapping(recipe.get("input")).size
            except ConfigError:
                input_hw = None
        info = cls(class_name=objects[0].class_name, size_m=objects[0].size_m, frame=frames,
                   keypoint_order=ckpt.get("keypoint_order", KEYPOINT_ORDER), mean=mean, std=std,
                   input_hw=input_hw, min_score=ckpt.get("min_score"), objects=objects)
        info.validate(path)
        return info

    def objects_metadata(self) -> list[dict[str, Any]]:
        """The objects as checkpoint / ONNX metadata entries (:meth:`ObjectInfo.to_dict`)."""
        return [o.to_dict(self.frame) for o in self.objects]

    def select(self, class_name: str) -> ModelInfo:
        """This info narrowed to one object (its own class_name and size_m); KeyError."""
        obj = self.objects[self.object_index(class_name)]
        return replace(self, class_name=obj.class_name, size_m=tuple(obj.size_m), objects=(obj,))


def objects_from_entries(entries: Sequence[Any], path: str | os.PathLike,
                         where: str = "objects") -> tuple[tuple[ObjectInfo, ...], str]:
    """(objects, their common frame) of a list of object entries; ModelFileError when an entry
    is malformed or the objects do not share one frame."""
    parsed = [object_from_dict(e, path, f"{where}[{k}]" if where == "objects" else where)
              for k, e in enumerate(entries)]
    frames = {f for _, f in parsed}
    if len(frames) != 1:
        raise ModelFileError(path, f"model metadata: the objects use different frames ({', '.join(sorted(frames))})")
    return tuple(o for o, _ in parsed), frames.pop()
