"""Ground truth for evaluation: the frames of a DOPE, HOPE or BOP dataset folder.

:func:`load_dataset` reads every annotated frame once (GT poses in metres, K, image size,
visibility, the depth path when there is one); :func:`assign_predictions` maps each prediction
record's ``image`` (relative path, absolute path, unique file name or stem, or BOP
``scene_id``/``im_id``) to its frame.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.io import bop as bop_io
from dope_hope.io.dope_json import list_dope_frames, read_dope_json, recorded_cuboid_size
from dope_hope.io.hope_json import list_hope_frames, read_hope_json
from dope_hope.io.layouts import dataset_layout
from dope_hope.io.predictions import Prediction

VISIB_GT_MIN = 0.1


# =========================================================================== dataset
@dataclass
class EvalFrame(FrameAnnotation):
    """One test image with its ground truth: a :class:`~dope_hope.annotation.FrameAnnotation`
    (GT in metres, mesh frame; ``source`` is the annotation file) plus how predictions name it.

    Attributes:
        key: unique id: image path relative to the dataset folder (posix).
        aliases: names a prediction may use for this image (relative paths, file name, stem).
    """

    key: str = ""
    aliases: set[str] = field(default_factory=set)


@dataclass
class Dataset:
    """Frames plus optional BOP targets {(scene_id, im_id, obj_id): inst_count}; ``name`` is
    the BOP dataset name (the folder above the split, e.g. "hope") for BOP datasets."""

    root: Path
    fmt: str
    frames: list[EvalFrame]
    targets: dict[tuple[int, int, int], int] | None = None
    name: str | None = None
    #: class -> ((3,) m cuboid the annotations record, the file recording it) (dope-hope synth data)
    cuboid_sizes: dict[str, tuple[np.ndarray, Path]] = field(default_factory=dict)


def _aliases(root: Path, *paths: Path | None) -> set[str]:
    out: set[str] = set()
    for p in paths:
        if p is None:
            continue
        try:
            rel = p.resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            rel = p.as_posix()
        out |= {rel, rel.rsplit(".", 1)[0] if "." in Path(rel).name else rel, p.name,
                p.name.split(".", 1)[0], str(p.resolve())}
    return out


def _subfolders(root: Path) -> list[Path]:
    return [root] + sorted(p for p in root.rglob("*") if p.is_dir())


def _frame_from_annotation(root: Path, ann, json_path: Path) -> EvalFrame:
    image = ann.image_path
    key_path = image if image is not None else json_path
    try:
        key = key_path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        key = key_path.as_posix()
    return EvalFrame(source=ann.source, key=key, K=ann.K, width=ann.width, height=ann.height,
                     objects=list(ann.objects), aliases=_aliases(root, image, json_path),
                     image_path=image, depth_path=ann.depth_path, depth_scale_m=ann.depth_scale_m)


def load_dataset(root: str | os.PathLike, fmt: str = "auto") -> Dataset:
    """Read the ground truth of a test set.

    Args:
        root: dataset folder (searched recursively for DOPE / HOPE frames).
        fmt: "auto" (the layout :func:`dope_hope.io.layouts.dataset_layout` finds, as
            ``dope-hope infer`` finds an image's camera), "dope" (``dope_hope.io.dope_json``),
            "hope" (``io.hope_json``) or "bop" (``io.bop``, a BOP split folder or a dataset
            folder with ``test/``).

    Raises:
        InputFileError: no frames found or a malformed annotation.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputFileError(root, "dataset folder not found")
    if fmt == "auto":
        fmt = dataset_layout(root)
    if fmt == "dope":
        frames, sizes = [], {}
        for p in (p for d in _subfolders(root) for p in list_dope_frames(d)):
            frame = _frame_from_annotation(root, read_dope_json(p), p)
            frames.append(frame)
            for name in {o.class_name for o in frame.objects} - set(sizes):
                size = recorded_cuboid_size(p, name)
                if size is not None:
                    sizes[name] = (size, p)
        ds = Dataset(root, fmt, frames, cuboid_sizes=sizes)
    elif fmt == "hope":
        frames = [_frame_from_annotation(root, read_hope_json(p), p)
                  for d in _subfolders(root) for p in list_hope_frames(d)]
        ds = Dataset(root, fmt, frames)
    elif fmt == "bop":
        ds = _load_bop(root)
    else:
        raise ConfigError(f"unknown dataset format {fmt!r}; use auto, dope, hope or bop")
    if not ds.frames:
        raise InputFileError(root, f"no {fmt}-format frames found (annotation + image pairs)")
    return ds


def _load_bop(root: Path) -> Dataset:
    """A BOP split folder (``<split>/<scene_id>/scene_gt.json`` ...) or a dataset folder with
    a ``test/`` split, through :mod:`dope_hope.io.bop`; targets from
    ``test_targets_bop19.json`` in the split or dataset folder when present."""
    split_dir = root
    if not bop_io.list_bop_scenes(root) and (root / "test").is_dir():
        split_dir = root / "test"
    frames = []
    for bf in bop_io.iter_bop_split(split_dir):
        ann = bf.annotation
        ids = f"{bf.scene_id:06d}/{bf.im_id:06d}"
        key = ids
        if ann.image_path is not None:
            key = ann.image_path.resolve().relative_to(split_dir.resolve()).as_posix()
        frames.append(EvalFrame(
            source=ann.source, key=key, K=ann.K, width=ann.width, height=ann.height, objects=list(ann.objects),
            aliases=_aliases(split_dir, ann.image_path) | {ids},
            image_path=ann.image_path, depth_path=ann.depth_path,
            depth_scale_m=ann.depth_scale_m, scene_id=bf.scene_id, im_id=bf.im_id))
    targets = None
    for candidate in (split_dir / "test_targets_bop19.json", split_dir.parent / "test_targets_bop19.json"):
        if candidate.is_file():
            targets = {(s, i, o): n for s, i, o, n in bop_io.read_test_targets(candidate)}
            break
    return Dataset(split_dir, "bop", frames, targets, name=split_dir.resolve().parent.name)


# =========================================================================== predictions
def assign_predictions(dataset: Dataset, preds: list[Prediction],
                       source: str | os.PathLike = "predictions"
                       ) -> tuple[list[list[Prediction]], int]:
    """Group predictions by dataset frame (index-aligned with ``dataset.frames``).

    A prediction's ``image`` is matched against each frame's aliases (relative path, path
    without suffix, file name, stem, absolute path); BOP rows by (scene_id, im_id). A
    prediction given only by BOP ids whose image is not in the dataset is ignored, as the BOP
    toolkit ignores estimates of images that are not targets.

    Returns:
        (predictions per frame, number ignored).

    Raises:
        InputFileError: a named image that is not in the dataset, or a name shared by two
        frames.
    """
    alias_map: dict[str, int] = {}
    ambiguous: set[str] = set()
    for i, f in enumerate(dataset.frames):
        for a in f.aliases:
            if a in alias_map and alias_map[a] != i:
                ambiguous.add(a)
            alias_map.setdefault(a, i)
    by_id = {(f.scene_id, f.im_id): i for i, f in enumerate(dataset.frames)
             if f.scene_id is not None and f.im_id is not None}
    out: list[list[Prediction]] = [[] for _ in dataset.frames]
    ignored = 0
    for p in preds:
        idx = None
        if p.image is not None:
            name = p.image.replace("\\", "/")
            candidates = [name, name.lstrip("./")]
            if os.path.isabs(name) or Path(name).exists():
                candidates.insert(0, str(Path(name).resolve()))
            for c in candidates:
                if c in ambiguous:
                    raise InputFileError(source, f"line {p.line}: image {p.image!r} names several "
                                                 f"frames of {dataset.root}; use its relative path")
                if c in alias_map:
                    idx = alias_map[c]
                    break
        if idx is None and p.scene_id is not None and p.im_id is not None:
            idx = by_id.get((p.scene_id, p.im_id))
            if idx is None and p.image is None:
                ignored += 1
                continue
        if idx is None:
            what = repr(p.image) if p.image is not None else f"scene {p.scene_id} image {p.im_id}"
            raise InputFileError(source, f"line {p.line}: image {what} is not in the dataset "
                                         f"{dataset.root} ({dataset.fmt} format)")
        out[idx].append(p)
    return out, ignored
