"""Where a run's frames come from: DOPE-format folders and BOP-format datasets, mixed freely.

Each ``--data`` / ``--val`` folder is read by its format (a BOP split or scene folder:
:mod:`dope_hope.io.bop_scenes`; anything else: DOPE JSON, :func:`~dope_hope.training.dataset.scan_frames`)
into the same :class:`~dope_hope.training.dataset.FrameRecord` list, with the same rules
(the run's classes, ``min_visibility``, frames without instances kept or not).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import InputFileError
from dope_hope.geometry import KEYPOINT_ORDER
from dope_hope.io.bop_scenes import bop_class_name, is_bop_dataset, iter_bop_frames
from dope_hope.io.dope_json import read_dope_json
from dope_hope.training.dataset import FrameRecord, class_index, frame_record, scan_frames


def scan_bop(folder: str | Path, class_names: Sequence[str], keypoint_order: str = KEYPOINT_ORDER,
             min_visibility: float = 0.0, include_empty: bool = True) -> list[FrameRecord]:
    """The records of a BOP split or scene folder: each obj_id is the class
    :func:`dope_hope.io.bop_scenes.bop_class_name` gives among ``class_names``."""
    names = list(class_names)
    want = class_index(names)
    records = []
    for frame in iter_bop_frames(folder, class_name=lambda obj_id: bop_class_name(obj_id, names)):
        record = frame_record(frame, Path(frame.source), want, keypoint_order, min_visibility)
        if include_empty or len(record.keypoints):
            records.append(record)
    return records


def scan_training_data(folders: Sequence[str | Path], class_names: str | Sequence[str],
                       keypoint_order: str = KEYPOINT_ORDER, min_visibility: float = 0.0,
                       include_empty: bool = True, progress: bool = False,
                       ) -> tuple[list[FrameRecord], list[tuple[Path, str]]]:
    """Records of every folder, in the order given (BOP datasets and DOPE folders alike).

    Returns:
        (records, bad): bad lists DOPE annotation files that could not be parsed
        (:func:`~dope_hope.training.dataset.scan_frames`).
    """
    names = [class_names] if isinstance(class_names, str) else list(class_names)
    records: list[FrameRecord] = []
    bad: list[tuple[Path, str]] = []
    dope: list[Path] = []

    def flush() -> None:
        if dope:
            found, unreadable = scan_frames(dope, names, keypoint_order, min_visibility, include_empty, progress)
            records.extend(found)
            bad.extend(unreadable)
            dope.clear()

    for folder in folders:
        if is_bop_dataset(folder):
            flush()
            records.extend(scan_bop(folder, names, keypoint_order, min_visibility, include_empty))
        else:
            dope.append(Path(folder))
    flush()
    return records, bad


def check_instances(records: Sequence[FrameRecord], class_names: Sequence[str], folders: Sequence[str | Path]) -> None:
    """InputFileError naming the folders unless every object of the run has an annotated
    instance among ``records``: an object without one would train a map group that only ever
    learns "absent" (a misspelt or missing object, or data of other objects)."""
    names = list(class_names)
    indices = [r.object_indices() for r in records if len(r.keypoints)]
    counts = np.bincount(np.concatenate(indices), minlength=len(names)) if indices else np.zeros(len(names), int)
    where = ", ".join(str(p) for p in folders)
    if not counts.any():
        raise InputFileError(where, f"no annotated instance of class {' / '.join(names)!r}")
    missing = [n for n, c in zip(names, counts) if c == 0]
    if missing:
        found = ", ".join(f"{n} {c}" for n, c in zip(names, counts) if c)
        raise InputFileError(where, f"no annotated instance of {', '.join(missing)} (--object), whose maps would "
                                    f"only learn 'absent'; instances found: {found}")


def record_annotations(records: Sequence[FrameRecord], folders: Sequence[str | Path],
                       class_names: Sequence[str]) -> list[FrameAnnotation]:
    """The whole annotation of each of ``records`` (read from ``folders``, as
    :func:`scan_training_data` found them), its instances of the run's classes named as
    ``class_names`` spells them (the annotations' spelling may differ in case)."""
    names = list(class_names)
    spelled = {n.lower(): n for n in names}
    wanted = {r.image_path.resolve() for r in records}
    bop: dict[Path, FrameAnnotation] = {}
    for folder in folders:
        if is_bop_dataset(folder):
            for frame in iter_bop_frames(folder, class_name=lambda obj_id: bop_class_name(obj_id, names)):
                if frame.image_path is not None and frame.image_path.resolve() in wanted:
                    bop[frame.image_path.resolve()] = frame
    out = []
    for record in records:
        frame = bop.get(record.image_path.resolve()) or read_dope_json(record.json_path)
        objects = [replace(o, class_name=spelled.get(o.class_name.lower(), o.class_name)) for o in frame.objects]
        out.append(replace(frame, objects=objects, image_path=record.image_path))
    return out
