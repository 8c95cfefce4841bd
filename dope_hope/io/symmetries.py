"""Symmetry declarations of objects: BOP ``models_info``-style JSON, one reader for every use.

A declaration holds the BOP fields (bop_toolkit ``docs/bop_datasets_format.md``)::

    "symmetries_discrete":   [[16 numbers: a 4x4 transform, row-major], ...]
    "symmetries_continuous": [{"axis": [x, y, z], "offset": [x, y, z]}, ...]

(optionally ``diameter``), either alone in the file (``model_info.json``, as beside the
official DOPE sample meshes with symmetries) or as one entry of a BOP ``models_info.json``
keyed by obj_id. Lengths (translations, offsets, diameter) are in the unit of the mesh it
belongs to: millimetres for BOP, centimetres beside a HOPE OBJ. A transform maps the model
onto itself, ``x' = R x + t``, in the model frame.

This module reads and finds declaration files; which one an object uses (the one resolution
order of training labels, ``dope-hope demo``, the evaluation tables and BOP AR) is
:func:`dope_hope.symmetry.resolve.resolve_symmetries`, and what a declaration means as
transforms is :mod:`dope_hope.symmetry.transforms`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dope_hope.errors import InputFileError
from dope_hope.geometry import UNIT_SCALE
from dope_hope.io.bop import parse_model_info
from dope_hope.io.jsonfields import JsonFields, load_json_object
from dope_hope.io.meshes import DEFAULT_UNITS

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


def mesh_units(mesh_path: str | os.PathLike, units: str | None = None) -> str:
    """The unit of a mesh file: ``units`` if given, else the default of its suffix (mm)."""
    return units or DEFAULT_UNITS.get(Path(mesh_path).suffix.lower(), "mm")


def bop_table_declaration(mesh_path: str | os.PathLike, units: str | None = None,
                          obj_id: int | None = None) -> SymmetryDeclaration | None:
    """The object's entry in a BOP ``models_info.json`` beside the mesh (obj_id from an
    ``obj_NNNNNN`` mesh name, else ``obj_id``), lengths in ``units`` (else the mesh's unit);
    None when there is no such file or entry."""
    path = Path(mesh_path).parent / DECLARATION_NAMES[1]
    stem = Path(mesh_path).stem
    if stem.startswith("obj_") and stem[4:].isdigit():
        obj_id = int(stem[4:])
    if obj_id is None or not path.is_file():
        return None
    data = load_json_object(path, "symmetry declaration")
    if str(obj_id) not in {str(int(k)) for k in data if str(k).isdigit()}:
        return None
    return read_declaration(path, mesh_units(mesh_path, units), obj_id)


def model_info_declaration(mesh_path: str | os.PathLike, units: str | None = None,
                           obj_id: int | None = None) -> SymmetryDeclaration | None:
    """``model_info.json`` (one object's declaration; ``obj_id`` picks the entry if it holds a
    table) beside the mesh, lengths in ``units`` (else the mesh's unit); None when there is none."""
    path = Path(mesh_path).parent / DECLARATION_NAMES[0]
    return read_declaration(path, mesh_units(mesh_path, units), obj_id) if path.is_file() else None
