"""Symmetry declarations of objects: BOP ``models_info``-style JSON, one reader for every use.

A declaration holds the BOP fields (bop_toolkit ``docs/bop_datasets_format.md``)::

    "symmetries_discrete":   [[16 numbers: a 4x4 transform, row-major], ...]
    "symmetries_continuous": [{"axis": [x, y, z], "offset": [x, y, z]}, ...]

(optionally ``diameter``), either alone in the file (``model_info.json``, as beside the
official DOPE sample meshes with symmetries) or as one entry of a BOP ``models_info.json``
keyed by obj_id. Lengths (translations, offsets, diameter) are in the unit of the mesh it
belongs to: millimetres for BOP, centimetres beside a HOPE OBJ. A transform maps the model
onto itself, ``x' = R x + t``, in the model frame.

Where a declaration comes from: a file named on the command line (``--symmetries``), else
``model_info.json`` beside the mesh (or ``models_info.json`` there, with the object's
obj_id). Training labels, ``dope-hope demo``, the evaluation tables and BOP AR all take it
from here; objects without one fall back on the HOPE catalog's category.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.io.bop import parse_model_info, symmetry_transforms
from dope_hope.io.jsonfields import JsonFields, load_json_object
from dope_hope.io.meshes import DEFAULT_UNITS, UNIT_SCALE

#: File names looked for beside a mesh: a single model's declaration, then BOP's table.
DECLARATION_NAMES = ("model_info.json", "models_info.json")
_FIELDS = ("symmetries_discrete", "symmetries_continuous", "diameter")


@dataclass
class SymmetryDeclaration:
    """One object's declared symmetries.

    Attributes:
        entry: the BOP fields as written (``symmetries_discrete``, ``symmetries_continuous``,
            ``diameter`` when given), already checked: what the BOP toolkit computes on
            (BOP19 scoring discretizes it with
            :func:`dope_hope.evaluation.metrics.symmetries_from_models_info`).
        units: length unit of ``entry`` ("m", "cm", "mm").
        source: the file (and entry) it was read from.
    """

    entry: dict[str, Any]
    units: str
    source: str

    @property
    def unit_m(self) -> float:
        """Metres per length unit of ``entry``."""
        return UNIT_SCALE[self.units]

    def transforms(self, step_deg: float = 1.0) -> np.ndarray:
        """(S, 4, 4) model-frame transforms in metres, identity first; continuous symmetries
        sampled every ``step_deg`` (90 gives the ones that can permute cuboid corners)."""
        info = parse_model_info(JsonFields(self.source), self.entry, "", self.units)
        return symmetry_transforms(info, step_deg)

    @property
    def diameter_m(self) -> float | None:
        d = self.entry.get("diameter")
        return None if d is None else float(d) * self.unit_m


def read_declaration(path: str | os.PathLike, units: str = "mm",
                     obj_id: int | None = None) -> SymmetryDeclaration:
    """Read a declaration file (module docstring); ``obj_id`` picks the entry of a table.

    Raises:
        InputFileError: missing or malformed file, a table without the entry, bad fields
            (the message names the file and the field).
    """
    path = Path(path)
    if units not in UNIT_SCALE:
        raise InputFileError(path, f"unknown unit {units!r}; use one of {sorted(UNIT_SCALE)}")
    data = load_json_object(path, "symmetry declaration")
    where = ""
    if data and all(str(k).isdigit() for k in data):
        if obj_id is None:
            if len(data) != 1:
                raise InputFileError(path, f"a models_info table of {len(data)} objects: cannot tell "
                                           "which entry is this object's")
            obj_id = int(next(iter(data)))
        entry = {int(k): v for k, v in data.items()}.get(int(obj_id))
        if entry is None:
            raise InputFileError(path, f"no entry for obj_id {obj_id}")
        where = str(obj_id)
    else:
        entry = data
    f = JsonFields(path)
    parse_model_info(f, entry, where, "mm")  # checks every field; the entry is kept as written
    kept = {k: entry[k] for k in _FIELDS if entry.get(k) is not None}
    return SymmetryDeclaration(kept, units, f"{path}" + (f" [{where}]" if where else ""))


def find_declaration(mesh_path: str | os.PathLike) -> Path | None:
    """``model_info.json`` / ``models_info.json`` in the mesh's folder, or None."""
    folder = Path(mesh_path).parent
    return next((folder / n for n in DECLARATION_NAMES if (folder / n).is_file()), None)


def mesh_units(mesh_path: str | os.PathLike, units: str | None = None) -> str:
    """The unit of a mesh file: ``units`` if given, else the default of its suffix (mm)."""
    return units or DEFAULT_UNITS.get(Path(mesh_path).suffix.lower(), "mm")


def declared_symmetries(explicit: str | os.PathLike | None = None,
                        mesh_path: str | os.PathLike | None = None, units: str | None = None,
                        obj_id: int | None = None) -> SymmetryDeclaration | None:
    """The declaration of one object: ``explicit`` (a file named by the user), else the one
    beside ``mesh_path``; None when neither exists (or a BOP table there has no entry for the
    object: ``obj_id``, else the ``obj_NNNNNN`` mesh name). Lengths are in ``units``, else
    the mesh's unit (its suffix's default), else millimetres (BOP)."""
    unit = mesh_units(mesh_path, units) if mesh_path is not None else (units or "mm")
    if explicit is not None:
        return read_declaration(explicit, unit, obj_id)
    if mesh_path is None:
        return None
    path = find_declaration(mesh_path)
    if path is None:
        return None
    if path.name == "models_info.json":
        stem = Path(mesh_path).stem
        if stem.startswith("obj_") and stem[4:].isdigit():
            obj_id = int(stem[4:])
        data = load_json_object(path, "symmetry declaration")
        if obj_id is None or str(obj_id) not in {str(int(k)) for k in data if str(k).isdigit()}:
            return None
    return read_declaration(path, unit, obj_id)
