"""The objects of a training run: their classes, checkpoint entries and label symmetries.

A run trains N >= 1 objects (``TrainJob.class_names``, channel-group order: object k owns
belief channels [9k, 9k+9) and affinity channels [16k, 16k+16)). One object keeps the
checkpoint and config of a one-object run exactly; several set ``model.num_objects`` and
write the checkpoint's ``objects`` list.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError
from dope_hope.io.bop_scenes import recorded_symmetry_fields
from dope_hope.io.symmetries import SymmetryDeclaration
from dope_hope.symmetry.labels import corner_permutations
from dope_hope.symmetry.resolve import ObjectSymmetries, label_symmetries, resolve_symmetries
from dope_hope.training.dataset import FrameRecord, relabel_symmetric
from dope_hope.training.settings import TrainConfig, TrainJob, object_info


@dataclass
class RunObject:
    """One object of a run.

    Attributes:
        name: class name; info: its checkpoint entry (class_name, size_m, frame[, symmetries]);
        size_source: where its cuboid size came from (in words); symmetry_source: its
        symmetries and where they come from (in words: ``ObjectSymmetries.describe``).
    """

    name: str
    info: dict[str, Any]
    size_source: str
    symmetry_source: str = "none"


def with_num_objects(recipe: TrainConfig, n: int) -> TrainConfig:
    """``recipe`` with ``model.num_objects = n``: its default 1 becomes the run's ``n``; another
    number than ``n`` (e.g. a resumed run's) is a ConfigError."""
    given = recipe.model.num_objects
    if given not in (1, n):
        raise ConfigError(f"model.num_objects is {given} but the run trains {n} object(s)")
    if given == n:
        return recipe
    return replace(recipe, model=replace(recipe.model, num_objects=int(n)))


def check_class_names(names: list[str]) -> None:
    """ConfigError for an empty name or one class twice (names compare case-insensitively)."""
    seen: set[str] = set()
    for name in names:
        if not name:
            raise ConfigError("--object NAME is required (the class to train)")
        if name.lower() in seen:
            raise ConfigError(f"--object: {name} is named twice")
        seen.add(name.lower())


def entry_mm(declaration: SymmetryDeclaration | None) -> dict[str, Any] | None:
    """A declaration's BOP fields in millimetres (the checkpoint's ``symmetries``), or None."""
    if declaration is None:
        return None
    to_mm = declaration.unit_m / 0.001
    entry = dict(declaration.entry)
    if entry.get("symmetries_discrete"):
        mats = [np.asarray(m, dtype=np.float64).reshape(4, 4) for m in entry["symmetries_discrete"]]
        for m in mats:
            m[:3, 3] *= to_mm
        entry["symmetries_discrete"] = [m.reshape(-1).tolist() for m in mats]
    if entry.get("symmetries_continuous"):
        entry["symmetries_continuous"] = [
            {"axis": list(c["axis"]), "offset": [float(v) * to_mm for v in c.get("offset", [0, 0, 0])]}
            for c in entry["symmetries_continuous"]]
    if entry.get("diameter") is not None:
        entry["diameter"] = float(entry["diameter"]) * to_mm
    return entry


def job_object_symmetries(job: TrainJob, name: str) -> ObjectSymmetries:
    """The object's symmetries in the one resolution order
    (:func:`~dope_hope.symmetry.resolve.resolve_symmetries`): ``--symmetries`` (one object),
    declarations beside its mesh, the catalog category, else what its mesh shows."""
    explicit = job.symmetries if len(job.class_names) == 1 else None
    return resolve_symmetries(name, job.mesh_of(name), explicit, job.unit_of(name))


def bop_symmetries(records: list[FrameRecord], object_index: int, name: str) -> dict[str, Any] | None:
    """The symmetry fields the ``models_info.json`` of a BOP dataset among the records declares
    for the object (:func:`dope_hope.io.bop_scenes.recorded_symmetry_fields`), or None."""
    for r in records:
        if r.json_path.name == "scene_gt.json" and np.any(r.object_indices() == object_index):
            return recorded_symmetry_fields(r.json_path, name)
    return None


def run_objects(job: TrainJob, records: list[FrameRecord]) -> list[RunObject]:
    """Each object's checkpoint entry (:func:`~dope_hope.training.settings.object_info`: mesh >
    dataset > catalog), with its symmetries (:func:`job_object_symmetries`: declared, or found on
    its mesh; else declared in a BOP dataset's models_info.json) when it is one of several
    objects (a one-object entry stays as it always was), and where they come from."""
    names = job.class_names
    out = []
    for k, name in enumerate(names):
        info, source = object_info(name, records, job.mesh_of(name), job.unit_of(name), k)
        found = job_object_symmetries(job, name)
        symmetry_source = found.describe()
        if len(names) > 1:  # a declaration, a BOP dataset's, then what the mesh shows
            symmetries = None if found.detected is not None else entry_mm(found.declaration)
            if symmetries is None:
                symmetries = bop_symmetries(records, k, name)
                if symmetries is not None:
                    symmetry_source = "declared in the BOP dataset's models_info.json"
            if symmetries is None:
                symmetries = entry_mm(found.declaration)
            if symmetries is not None:
                info = {**info, "symmetries": symmetries}
        out.append(RunObject(info["class_name"], info, source, symmetry_source))
    return out


def relabel_objects(setting: Any, job: TrainJob, objects: list[RunObject],
                    record_sets: list[list[FrameRecord]]) -> tuple[list[list[FrameRecord]], int, list[str]]:
    """Symmetry-aware labels (config ``targets.symmetry``) for each object with its own
    symmetries (:func:`~dope_hope.symmetry.resolve.label_symmetries`): every record set
    relabelled object by object.

    Returns:
        (record sets, the largest number of corner-permuting symmetries, log lines).
    """
    if len(objects) > 1 and job.symmetries is not None:
        raise ConfigError(f"--symmetries {job.symmetries}: one file for {len(objects)} objects; put each "
                          "object's model_info.json beside its mesh")
    most, lines = 1, []
    for k, obj in enumerate(objects):
        symmetry = label_symmetries(setting, obj.name, job.symmetries if len(objects) == 1 else None,
                                    job.mesh_of(obj.name), job.unit_of(obj.name))
        if symmetry is None:
            continue
        rots, perms = corner_permutations(np.asarray(obj.info["size_m"]), symmetry[0])
        most = max(most, len(perms))
        index = None if len(objects) == 1 else k
        record_sets = [relabel_symmetric(rs, rots, perms, index) for rs in record_sets]
        lines.append(("" if index is None else f"{obj.name}: ")
                     + f"{symmetry[1]}, {len(perms)} corner-permuting symmetries")
    return record_sets, most, lines


def checkpoint_objects(objects: list[RunObject]) -> dict[str, Any] | list[dict[str, Any]]:
    """What ``save_checkpoint`` records: the one entry of a one-object run, else the list."""
    return objects[0].info if len(objects) == 1 else [o.info for o in objects]


def object_mesh_paths(job: TrainJob) -> dict[str, str | None]:
    """{class: mesh path as text} of the run's objects (for the checkpoint's job record)."""
    return {n: None if job.mesh_of(n) is None else str(Path(job.mesh_of(n))) for n in job.class_names}
