"""A round's labelled frames on disk, in the DOPE format, and their contact sheet.

The frames are read once into ``frames/`` (``NNNNNN.png`` RGB, ``NNNNNN.depth.png`` uint16 mm,
``index.json`` of their names and cameras, written last: :class:`FrameStore`). A round's
folder (``labels/``) holds, for each frame with at least one confirmed label, links to its
``NNNNNN.png`` and ``NNNNNN.depth.png`` there and its ``NNNNNN.json``
(:func:`dope_hope.io.dope_json.write_dope_json`: the confirmed labels as objects, the object's
``cuboid`` and, under ``adapt``, each label's evidence, the rejected poses and the source frame's
name), so `dope-hope train`, `infer` and `evaluate` read it as any DOPE folder; a frame without
a confirmed label is left out (as a training frame it would teach "absent"). Beside them,
``labels.jsonl`` (every frame: kept and rejected poses with their evidence) and
``summary.json`` (the counts, written last). The set is written into a temporary folder and
renamed into place at the end: a folder ``labels/`` is always a whole one.
"""
from __future__ import annotations

import json
import os
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dope_hope.adaptation.labelling import LabelledFrame, PoseLabel
from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import read_depth_m, read_rgb, write_depth_mm, write_rgb
from dope_hope.io.streams import Frame
from dope_hope.refine.depth import DepthImage
from dope_hope.synth.writer import frame_paths
from dope_hope.viz import draw_cuboid, draw_label, montage

#: Tiles of kept and of rejected labels on the contact sheet, at most.
PREVIEW_TILES = 12
#: Colours of the contact sheet: kept (green), rejected (red).
KEPT_COLOR, REJECTED_COLOR = (0, 220, 0), (230, 40, 40)


@dataclass(frozen=True)
class LabelCounts:
    """A round's label counts: frames; detected / carried labels kept and rejected; frames with
    a label; frames where the model found nothing the depth confirms (missed) and those of
    them a carried label fills."""

    frames: int
    detected_kept: int
    detected_rejected: int
    carried_kept: int
    carried_rejected: int
    labelled_frames: int
    missed_frames: int
    filled_frames: int

    @classmethod
    def of(cls, frames: Sequence[LabelledFrame]) -> LabelCounts:
        def n(kept: bool, source: str) -> int:
            return sum(1 for f in frames for lab in (f.kept if kept else f.rejected) if lab.evidence.source == source)

        missed = [f for f in frames if not f.detected]
        return cls(len(frames), n(True, "detected"), n(False, "detected"), n(True, "carried"), n(False, "carried"),
                   sum(1 for f in frames if f.kept), len(missed), sum(1 for f in missed if f.kept))


class FrameStore:
    """The sequence's frames on disk (module docstring), read from the source once.

    ``folder``: ``frames/``. :attr:`complete`: ``index.json`` exists (every frame written).
    """

    def __init__(self, folder: Path):
        self.folder = folder
        self.entries: list[dict] = []
        index = folder / "index.json"
        if index.is_file():
            self.entries = json.loads(index.read_text())["frames"]

    @property
    def complete(self) -> bool:
        return (self.folder / "index.json").is_file()

    def add(self, frame: Frame) -> None:
        """Write one frame (RGB, depth metres as uint16 mm) and note its name and camera."""
        i = len(self.entries)
        paths = frame_paths(self.folder, i)
        write_rgb(paths["rgb"], frame.rgb)
        write_depth_mm(paths["depth"], frame.depth if frame.depth is not None else np.zeros(frame.rgb.shape[:2]))
        self.entries.append({"name": frame.name, "K": np.asarray(frame.K, np.float64).tolist(),
                             "hw": list(frame.rgb.shape[:2])})

    def finish(self, source: str) -> None:
        """Write ``index.json``: the store is complete."""
        atomic_write_text(self.folder / "index.json", json.dumps({"source": source, "frames": self.entries}) + "\n")

    def __len__(self) -> int:
        return len(self.entries)

    def frame(self, i: int) -> Frame:
        """Frame ``i`` read back (RGB, depth in metres, 0 = none)."""
        paths, e = frame_paths(self.folder, i), self.entries[i]
        return Frame(i, float(i), e["name"], read_rgb(paths["rgb"]), np.asarray(e["K"], np.float64),
                     read_depth_m(paths["depth"], 0.001))

    def depth(self, i: int) -> DepthImage:
        """Frame ``i``'s depth with its K."""
        e = self.entries[i]
        return DepthImage.from_raw(read_depth_m(frame_paths(self.folder, i)["depth"], 0.001),
                                   np.asarray(e["K"], np.float64), 0.001, 1.0, tuple(e["hw"]))


def _annotation(lf: LabelledFrame, path: Path) -> FrameAnnotation:
    objects = [ObjectAnnotation(lab.class_name, lab.R, lab.t, projected_cuboid=lab.projected_2d,
                                bbox_xyxy=lab.bbox_2d) for lab in lf.kept]
    return FrameAnnotation(path, lf.K, lf.hw[1], lf.hw[0], objects)


def write_label_set(store: FrameStore, folder: Path, frames: Sequence[LabelledFrame],
                    cuboids: Mapping[str, tuple[np.ndarray, np.ndarray]], extra: Mapping | None = None,
                    preview: Path | None = None) -> LabelCounts:
    """Write the label set of the store's frames into ``folder`` (module docstring; built in
    ``folder.partial`` and renamed into place) and the contact sheet to ``preview`` (when
    given). ``cuboids``: class -> (size (3,), centre (3,)) metres, mesh frame. ``extra``: what
    the summary also records (the model, the settings)."""
    staging = folder.with_name(folder.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    if preview is not None:
        write_contact_sheet(store, frames, preview)
    for lf in frames:
        if not lf.kept:
            continue
        paths, source = frame_paths(staging, lf.index), frame_paths(store.folder, lf.index)
        for key in ("rgb", "depth"):
            os.symlink(source[key].resolve(), paths[key])
        boxes = [{"class": c, "size_m": [float(v) for v in cuboids[c][0]], "center_m": [float(v) for v in cuboids[c][1]],
                  "frame": "mesh (axis-aligned bounding box)"} for c in dict.fromkeys(lab.class_name for lab in lf.kept)]
        write_dope_json(paths["json"], _annotation(lf, paths["json"]), extra={
            "cuboid": boxes[0] if len(boxes) == 1 else boxes,
            "adapt": {"source_frame": lf.name, "labels": [lab.evidence.to_json() for lab in lf.kept],
                      "rejected": [lab.to_json() for lab in lf.rejected]}})
    lines = [json.dumps({"index": lf.index, "name": lf.name, "kept": [lab.to_json() for lab in lf.kept],
                         "rejected": [lab.to_json() for lab in lf.rejected]}) for lf in frames]
    atomic_write_text(staging / "labels.jsonl", "".join(line + "\n" for line in lines))
    counts = LabelCounts.of(frames)
    atomic_write_text(staging / "summary.json", json.dumps({"counts": counts.__dict__, **dict(extra or {})},
                                                           indent=1) + "\n")
    if folder.exists():
        shutil.rmtree(folder)
    os.replace(staging, folder)
    return counts


def _tile(rgb: np.ndarray, lab: PoseLabel, kept: bool) -> np.ndarray:
    img = draw_cuboid(rgb, lab.projected_2d, KEPT_COLOR if kept else REJECTED_COLOR)
    ev = lab.evidence
    head = f"{'kept' if kept else 'rejected'} {ev.source} s{ev.score:.2f} d{ev.support:.2f} e{ev.edge:.2f}"
    img = draw_label(img, head)
    return img if kept else draw_label(img, ev.reason[:60], (4, img.shape[0] - 24))


def write_contact_sheet(store: FrameStore, frames: Sequence[LabelledFrame], path: Path) -> Path | None:
    """``path``: up to :data:`PREVIEW_TILES` kept and as many rejected labels, each on its frame
    (read from ``store``) with its cuboid, its evidence and (rejected) the reason; kept
    ones first, spread over the sequence. None when there is no label at all."""
    def spread(items: list) -> list:
        if len(items) <= PREVIEW_TILES:
            return items
        return [items[int(k)] for k in np.linspace(0, len(items) - 1, PREVIEW_TILES).round()]

    kept = spread([(lf, lab, True) for lf in frames for lab in lf.kept])
    rejected = spread([(lf, lab, False) for lf in frames for lab in lf.rejected])
    tiles = []
    for lf, lab, is_kept in kept + rejected:
        rgb = read_rgb(frame_paths(store.folder, lf.index)["rgb"])
        tiles.append(_tile(rgb, lab, is_kept))
    if not tiles:
        return None
    h, w = tiles[0].shape[:2]
    scale = min(1.0, 320.0 / w)
    write_rgb(path, montage(tiles, cols=4, tile_hw=(int(h * scale), int(w * scale))))
    return path
