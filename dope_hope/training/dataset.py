"""Training data: a torch Dataset over DOPE-format folders (and BOP-format datasets:
:mod:`dope_hope.io.bop_scenes`).

One frame becomes one item, for a model of N objects (N = 1: one class):

* ``image``: (3, H, W) float32, ImageNet-normalized RGB at the training input size;
* ``belief`` (9N, h, w) and ``affinity`` (16N, h, w): per object k (channels [9k, 9k+9) and
  [16k, 16k+16)) :func:`dope_hope.maps.targets.make_targets` of the augmented keypoints
  (:mod:`~dope_hope.training.augment`) of that object's instances at the head's stride; all
  zero for an object absent from the frame;
* ``keypoints``: (max_instances, 9, 2) float32 input-image pixels of the instances of the
  classes, NaN where padded or where the keypoint left the image (what validation scores);
* ``classes``: (max_instances,) int64 object index of each ``keypoints`` row, -1 where padded;
* ``index`` (int) and ``bad_files`` (list of image files that could not be read and were
  replaced by another frame; the trainer reports each once).

The random draws of an item come from ``numpy.random.default_rng((seed, epoch, index))``
only, so an item is a pure function of (seed, epoch, index) whatever process or worker builds
it; :class:`EpochSampler` hands out ``(epoch, index)`` pairs so that DataLoader workers need no
shared state.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset, Sampler
from tqdm import tqdm

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import ConfigError, DopeHopeError, InputFileError
from dope_hope.geometry import (
    KEYPOINT_ORDER,
    LEGACY_KEYPOINT_ORDER,
    LEGACY_TO_CURRENT_INDEX,
    NUM_KEYPOINTS,
    legacy_keypoints_to_current,
)
from dope_hope.io.dope_json import find_image, list_dope_frames, read_dope_json
from dope_hope.io.images import image_size, read_rgb
from dope_hope.maps.targets import make_targets
from dope_hope.model.info import group_channels
from dope_hope.model.network import normalize_image
from dope_hope.symmetry.labels import camera_direction, canonical_keypoints
from dope_hope.training.augment import AugmentParams, augment
from dope_hope.training.frame_cache import FrameCache

log = logging.getLogger(__name__)


_REPORTED: set[str] = set()


def report_bad_file(path: str | Path, problem: str) -> bool:
    """Log a skipped file once per process (later calls for the same path are silent)."""
    key = str(path)
    if key in _REPORTED:
        return False
    _REPORTED.add(key)
    log.warning("skipping %s: %s", key, problem)
    return True


# --------------------------------------------------------------------------- keypoint order
def convert_keypoint_order(keypoints: np.ndarray, from_order: str, to_order: str) -> np.ndarray:
    """Reorder (..., 9, 2) keypoints between "dope-current" and "dope-legacy".

    The permutation is :data:`dope_hope.geometry.LEGACY_TO_CURRENT_INDEX`.

    Raises:
        ConfigError: an order name that is neither.
    """
    known = (KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER)
    for name in (from_order, to_order):
        if name not in known:
            raise ConfigError(f"unknown keypoint order {name!r}; known: {', '.join(known)}")
    kp = np.asarray(keypoints)
    if from_order == to_order:
        return kp
    if from_order == LEGACY_KEYPOINT_ORDER:
        return legacy_keypoints_to_current(kp)
    return kp[..., LEGACY_TO_CURRENT_INDEX, :]  # current[LEGACY_TO_CURRENT_INDEX[k]] = legacy[k]


# --------------------------------------------------------------------------- dataset
@dataclass
class FrameRecord:
    """What the dataset keeps per frame (the JSON is parsed once, at init)."""

    json_path: Path
    image_path: Path
    keypoints: np.ndarray  # (I, 9, 2) float64 in the model's keypoint order
    #: (I, 3) unit camera direction in each instance's object frame (NaN without a pose);
    #: what symmetry-aware relabelling (dope_hope.symmetry.labels) decides on.
    view_dirs: np.ndarray | None = None
    #: (I,) int object index of each instance in the run's object list (None: all object 0).
    classes: np.ndarray | None = None

    def object_indices(self) -> np.ndarray:
        """(I,) int object index of each instance."""
        return self.classes if self.classes is not None else np.zeros(len(self.keypoints), np.int64)


def class_index(class_names: str | Sequence[str]) -> dict[str, int]:
    """{lower-case class name: object index} of a run's object list (one name or several)."""
    names = [class_names] if isinstance(class_names, str) else list(class_names)
    return {n.lower(): k for k, n in enumerate(names)}


def instance_kept(visibility: float | None, visible_pixels: int | None, min_visibility: float) -> bool:
    """The rule for a training instance's visibility: a recorded fraction must be positive and
    >= ``min_visibility``; a recorded pixel count (BlenderProc) positive."""
    if visibility is not None and (visibility <= 0 or visibility < min_visibility):
        return False
    return visible_pixels is None or visible_pixels > 0


def frame_record(frame: FrameAnnotation, annotation_path: Path, want: dict[str, int],
                 keypoint_order: str = KEYPOINT_ORDER, min_visibility: float = 0.0) -> FrameRecord:
    """The record of one annotated frame (any reader's FrameAnnotation): the instances of the
    run's classes (``want``: :func:`class_index`) with a projected cuboid that pass
    :func:`instance_kept`, keypoints in ``keypoint_order``.

    Raises:
        InputFileError: no image beside the annotation.
    """
    kps: list[np.ndarray] = []
    dirs: list[np.ndarray] = []
    classes: list[int] = []
    for obj in frame.objects:
        k = want.get(obj.class_name.lower())
        if k is None or obj.projected_cuboid is None:
            continue
        if not instance_kept(obj.visibility, obj.visible_pixels, min_visibility):
            continue
        kp = np.asarray(obj.projected_cuboid, dtype=np.float64).reshape(NUM_KEYPOINTS, 2)
        kps.append(convert_keypoint_order(kp, obj.keypoint_order, keypoint_order))
        dirs.append(camera_direction(obj.R, obj.t))
        classes.append(k)
    image = frame.image_path if frame.image_path is not None else find_image(annotation_path)
    if image is None:
        raise InputFileError(annotation_path, "no image beside this annotation")
    return FrameRecord(annotation_path, Path(image),
                       np.stack(kps) if kps else np.zeros((0, NUM_KEYPOINTS, 2)),
                       np.stack(dirs) if dirs else np.zeros((0, 3)), np.array(classes, np.int64))


def scan_frames(
    folders: Sequence[str | Path], class_name: str | Sequence[str], keypoint_order: str = KEYPOINT_ORDER,
    min_visibility: float = 0.0, include_empty: bool = True, progress: bool = False,
) -> tuple[list[FrameRecord], list[tuple[Path, str]]]:
    """Parse every DOPE JSON of the folders once.

    Objects are kept when their class is ``class_name`` or one of the run's class names
    (case-insensitive; the record's ``classes`` give each instance's index), they carry a
    projected cuboid and their visibility (when recorded) is positive and >= min_visibility;
    a recorded pixel count instead of a fraction (BlenderProc) must be positive, as in the
    official DOPE loader, and ``min_visibility`` cannot apply to it.
    Keypoints are converted to ``keypoint_order``.

    Returns:
        (records, bad) where bad lists (json path, problem) of files that could not be parsed;
        each is logged once, here.

    Raises:
        InputFileError: a folder that does not exist or holds no DOPE frames.
    """
    want = class_index(class_name)
    records: list[FrameRecord] = []
    bad: list[tuple[Path, str]] = []
    paths: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            raise InputFileError(folder, "data folder not found")
        found = list_dope_frames(folder)
        if not found:
            raise InputFileError(folder, "no DOPE frames (NNNNNN.json beside an image) in this folder")
        paths.extend(found)
    iterator: Any = paths
    if progress and len(paths) > 2000:
        iterator = tqdm(paths, desc="scanning annotations", unit="file", leave=False)
    for path in iterator:
        try:
            frame = read_dope_json(path)
        except (DopeHopeError, ValueError, KeyError, TypeError, OSError) as exc:
            problem = getattr(exc, "problem", None) or (str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            bad.append((Path(path), problem))
            report_bad_file(path, f"unreadable annotation ({problem})")
            continue
        record = frame_record(frame, Path(path), want, keypoint_order, min_visibility)
        if include_empty or len(record.keypoints):
            records.append(record)
    return records, bad


class DopeDataset(Dataset):
    """Frames of the run's object classes (DOPE-format folders, BOP datasets), as network
    inputs + targets (a belief/affinity group per object).

    Args:
        records: from :func:`scan_frames` (or :meth:`from_folders`).
        input_hw: (H, W) network input size, pixels (multiples of 8).
        stride: the head's map stride (8 or 1).
        sigma, radius: target parameters, map pixels (config ``targets``).
        augment: ranges; ``augment.enabled`` False for validation.
        seed: base of the per-item RNG ``default_rng((seed, epoch, index))``.
        max_instances: rows of the padded ``keypoints`` output.
        num_objects: N, the belief/affinity groups of the targets (records' ``classes``).
        frame_cache_mb: memory for decoded frames shared with forked workers, MiB
            (:class:`~dope_hope.training.frame_cache.FrameCache`; 0: decode every time).
    """

    def __init__(
        self, records: list[FrameRecord], input_hw: tuple[int, int], stride: int,
        sigma: float, radius: float, augment: AugmentParams | None = None, seed: int = 0,
        max_instances: int = 8, num_objects: int = 1, frame_cache_mb: float = 0.0,
    ):
        self.records = records
        self.input_hw = (int(input_hw[0]), int(input_hw[1]))
        if self.input_hw[0] % 8 or self.input_hw[1] % 8:
            raise ConfigError(f"input size {list(self.input_hw)} must be multiples of 8")
        self.stride = int(stride)
        self.sigma = float(sigma)
        self.radius = float(radius)
        self.augment = augment if augment is not None else AugmentParams(enabled=False)
        self.seed = int(seed)
        self.max_instances = int(max_instances)
        self.num_objects = int(num_objects)
        self.epoch = 0
        self._bad_images: set[int] = set()
        self.frame_cache = self._make_cache(frame_cache_mb)

    def _make_cache(self, budget_mb: float) -> FrameCache | None:
        """A cache sized by the first readable frame (its header), or None."""
        if budget_mb <= 0 or not self.records:
            return None
        try:
            w, h = image_size(self.records[0].image_path)
        except DopeHopeError:
            return None  # the first read reports the file
        return FrameCache(len(self.records), (h, w), budget_mb)

    @classmethod
    def from_folders(cls, folders: Sequence[str | Path], class_name: str, **kwargs: Any) -> DopeDataset:
        """Scan folders (see :func:`scan_frames`) and build the dataset; kwargs go to __init__."""
        records, _ = scan_frames(folders, class_name)
        return cls(records, **kwargs)

    def __len__(self) -> int:
        return len(self.records)

    def set_epoch(self, epoch: int) -> None:
        """Epoch used for plain integer indices (samplers may pass (epoch, index) instead)."""
        self.epoch = int(epoch)

    def item_rng(self, epoch: int, index: int) -> np.random.Generator:
        return np.random.default_rng((self.seed, int(epoch), int(index)))

    def _load(self, index: int) -> np.ndarray | None:
        rec = self.records[index]
        if self.frame_cache is not None and (kept := self.frame_cache.get(index)) is not None:
            return kept
        try:
            rgb = read_rgb(rec.image_path)
            if self.frame_cache is not None:
                self.frame_cache.put(index, rgb)
            return rgb
        except (DopeHopeError, OSError, cv2.error) as exc:
            if index not in self._bad_images:
                self._bad_images.add(index)
                if torch.utils.data.get_worker_info() is None:  # in workers the trainer reports
                    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    report_bad_file(rec.image_path, f"unreadable image ({problem}), replaced by another frame")
            return None

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        epoch, index = (int(key[0]), int(key[1])) if isinstance(key, (tuple, list)) else (self.epoch, int(key))
        n = len(self.records)
        bad_files: list[str] = []
        rgb = None
        src = index
        for attempt in range(n):
            src = (index + attempt) % n
            if src in self._bad_images and attempt < n - 1:
                bad_files.append(str(self.records[src].image_path))
                continue
            rgb = self._load(src)
            if rgb is not None:
                break
            bad_files.append(str(self.records[src].image_path))
        if rgb is None:
            raise InputFileError(self.records[index].image_path, "no readable image in the whole dataset")
        rec = self.records[src]
        return self.make_item(rgb, rec.keypoints, self.item_rng(epoch, index),
                              index=index, bad_files=bad_files, classes=rec.object_indices())

    def make_item(self, rgb: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator | None,
                  index: int = -1, bad_files: list[str] | None = None,
                  classes: np.ndarray | None = None) -> dict[str, Any]:
        """Augment one image + keypoints (``classes``: (I,) object index of each instance,
        default all 0) and build the item dict (see the module docstring)."""
        img, kp, _ = augment(rgb, keypoints, self.input_hw, self.augment,
                             rng if self.augment.enabled else None)
        H, W = img.shape[:2]  # the input size, or the augmentation's object-centred crop
        cls = np.zeros(len(kp), np.int64) if classes is None else np.asarray(classes, np.int64)
        belief, affinity = self.object_targets(kp, cls, (H, W))
        out_kp = np.full((self.max_instances, NUM_KEYPOINTS, 2), np.nan, np.float32)
        out_cls = np.full(self.max_instances, -1, np.int64)
        m = min(len(kp), self.max_instances)
        if m:
            vis = kp[:m].copy()
            outside = ~((vis[..., 0] >= -0.5) & (vis[..., 0] < W - 0.5)
                        & (vis[..., 1] >= -0.5) & (vis[..., 1] < H - 0.5))
            vis[outside] = np.nan
            out_kp[:m] = vis
            out_cls[:m] = cls[:m]
        return {
            "image": normalize_image(img),
            "belief": torch.from_numpy(belief),
            "affinity": torch.from_numpy(affinity),
            "keypoints": torch.from_numpy(out_kp),
            "classes": torch.from_numpy(out_cls),
            "index": index,
            "bad_files": list(bad_files or []),
        }


    def object_targets(self, keypoints: np.ndarray, classes: np.ndarray,
                       image_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Belief (9N, h, w) and affinity (16N, h, w): object k's group made from its instances
        (``classes == k``) alone, all zero when it has none."""
        n = self.num_objects
        if n == 1:
            return make_targets(keypoints, image_hw, self.stride, self.sigma, self.radius)
        maps = None
        for k in range(n):
            belief, affinity = make_targets(keypoints[classes == k], image_hw, self.stride, self.sigma, self.radius)
            if maps is None:
                maps = np.zeros((n * (len(belief) + len(affinity)),) + belief.shape[1:], np.float32)
            maps[group_channels(k, n)] = np.concatenate([belief, affinity], axis=0)
        return maps[:NUM_KEYPOINTS * n], maps[NUM_KEYPOINTS * n:]


def collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack tensors, gather ``index`` into a tensor and concatenate ``bad_files``."""
    out: dict[str, Any] = {}
    for key in ("image", "belief", "affinity", "keypoints", "classes"):
        out[key] = torch.stack([it[key] for it in items])
    out["index"] = torch.tensor([it["index"] for it in items], dtype=torch.long)
    out["bad_files"] = [f for it in items for f in it["bad_files"]]
    return out


# --------------------------------------------------------------------------- sampling
class EpochSampler(Sampler):
    """Yields ``(epoch, index)``: a shuffle that is a function of (seed, epoch) only.

    Shards like ``DistributedSampler`` (the permutation padded to a multiple of
    ``world_size``, rank r takes every world_size-th entry from r) and can skip the first
    ``skip`` samples of this rank's share, which is how a resumed run continues mid-epoch.
    """

    def __init__(self, n: int, seed: int = 0, shuffle: bool = True, rank: int = 0, world_size: int = 1):
        if n <= 0:
            raise ValueError("EpochSampler needs a non-empty dataset")
        self.n, self.seed, self.shuffle = int(n), int(seed), bool(shuffle)
        self.rank, self.world_size = int(rank), int(world_size)
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.epoch, self.skip = int(epoch), int(skip)

    def indices(self) -> list[int]:
        """This rank's indices for the current epoch (before skipping)."""
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            order = torch.randperm(self.n, generator=g).tolist()
        else:
            order = list(range(self.n))
        per_rank = math.ceil(self.n / self.world_size)
        total = per_rank * self.world_size
        order = (order * math.ceil(total / self.n))[:total]
        return order[self.rank:total:self.world_size]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        for i in self.indices()[self.skip:]:
            yield (self.epoch, i)

    def __len__(self) -> int:
        return max(0, math.ceil(self.n / self.world_size) - self.skip)


def relabel_symmetric(records: list[FrameRecord], rotations: np.ndarray,
                      permutations: np.ndarray, object_index: int | None = None) -> list[FrameRecord]:
    """Records with each instance's keypoints in the canonical order of its view (see
    :mod:`dope_hope.symmetry.labels`); ``rotations``/``permutations`` from
    :func:`~dope_hope.symmetry.labels.corner_permutations` (of one object's
    symmetries: with ``object_index`` only that object's instances are relabelled). Instances
    without a recorded pose keep their order."""
    out = []
    for r in records:
        dirs = r.view_dirs if r.view_dirs is not None else np.full((len(r.keypoints), 3), np.nan)
        kp = canonical_keypoints(r.keypoints, dirs, rotations, permutations)
        if object_index is not None:
            mine = r.object_indices() == object_index
            kp = np.where(mine[:, None, None], kp, r.keypoints)
        out.append(replace(r, keypoints=kp))
    return out


def split_records(records: list[FrameRecord], val_fraction: float, seed: int) -> tuple[list[FrameRecord], list[FrameRecord]]:
    """Deterministic train/val split (a seeded shuffle of the sorted records); val has >= 1."""
    if len(records) < 2:
        raise ConfigError(f"need at least 2 frames to split off a validation set, got {len(records)}; pass --val")
    n_val = min(len(records) - 1, max(1, int(round(val_fraction * len(records)))))
    order = np.random.default_rng(seed).permutation(len(records))
    val_idx = set(order[:n_val].tolist())
    train = [r for i, r in enumerate(records) if i not in val_idx]
    val = [r for i, r in enumerate(records) if i in val_idx]
    return train, val
