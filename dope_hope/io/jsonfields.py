"""Checked access to parsed JSON: every problem becomes ``InputFileError(path, "<field>: ...")``.

Shared by the JSON readers (DOPE, HOPE, BOP) so that their messages read alike, e.g.
``frame.json: objects[0].projected_cuboid: expected 9 points, got 8``.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.io.paths import require_file


class JsonFields:
    """Field access that raises ``InputFileError(path, "<field>: <problem>")``."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def fail(self, field: str, problem: str) -> InputFileError:
        return InputFileError(self.path, f"{field}: {problem}")

    def get(self, obj: dict, key: str, where: str) -> Any:
        if not isinstance(obj, dict):
            raise self.fail(where or "top level", f"expected an object, got {type(obj).__name__}")
        if key not in obj or obj[key] is None:
            raise self.fail(f"{where}.{key}" if where else key, "missing field")
        return obj[key]

    def array(self, value: Any, field: str, shape: tuple[int, ...], rows: str = "points",
              cols: str = "coordinates per point") -> np.ndarray:
        """Numeric array of ``shape``; the first mismatching axis is named in the error."""
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(field, "expected a rectangular array of numbers") from None
        if arr.ndim != len(shape) or arr.shape != shape:
            if len(shape) == 2 and arr.ndim >= 1 and arr.shape[0] != shape[0]:
                raise self.fail(field, f"expected {shape[0]} {rows}, got {arr.shape[0]}")
            if len(shape) == 2 and arr.ndim == 2:
                raise self.fail(field, f"expected {shape[1]} {cols}, got {arr.shape[1]}")
            raise self.fail(field, f"expected shape {shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise self.fail(field, "contains NaN or infinity")
        return arr

    def number(self, value: Any, field: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(field, f"expected a finite number, got {value!r}")
        return float(value)

    def positive_number(self, value: Any, field: str) -> float:
        v = self.number(value, field)
        if v <= 0:
            raise self.fail(field, f"must be positive, got {value!r}")
        return v

    def positive_int(self, value: Any, field: str) -> int:
        if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
                or value <= 0 or value != int(value)):
            raise self.fail(field, f"expected a positive integer, got {value!r}")
        return int(value)


def read_text_file(path: str | os.PathLike, what: str = "file") -> str:
    """The text of a UTF-8 file; missing or not UTF-8 -> InputFileError naming the file."""
    path = require_file(path, what)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputFileError(path, "not a UTF-8 text file") from None


def load_json(path: str | os.PathLike, what: str = "annotation file") -> Any:
    """Parse a UTF-8 JSON file; missing or malformed -> InputFileError naming the file."""
    path = Path(path)
    text = read_text_file(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"malformed JSON (line {exc.lineno}: {exc.msg})") from None


def load_json_object(path: str | os.PathLike, what: str = "annotation file") -> dict:
    """:func:`load_json` for files whose top level must be a JSON object."""
    data = load_json(path, what)
    if not isinstance(data, dict):
        raise InputFileError(path, f"top level: expected a JSON object, got {type(data).__name__}")
    return data
