"""BOP19 submission files: ``METHOD_DATASET-SPLIT.csv`` with one pose estimate per line.

Format (BOP Challenge 2019+, ``docs/bop_challenge_2019.md`` of the BOP toolkit)::

    scene_id,im_id,obj_id,score,R,t,time
    1,0,11,0.93,r11 r12 r13 r21 r22 r23 r31 r32 r33,tx ty tz,0.153

* ``R``: the 3x3 rotation, row-major, 9 numbers separated by spaces (model -> camera); the
  reader refuses a matrix that is no rotation (:func:`dope_hope.geometry.checked_rotation`)
  and keeps the numbers as written (the BOP toolkit scores them as written);
* ``t``: translation in **millimetres**, 3 numbers separated by spaces (metres in memory, and
  the millimetres as written in ``t_mm``, which BOP19 scoring uses);
* ``time``: seconds spent on the whole image, the same value on every line of an image
  (``-1`` when unknown);
* the file name is ``METHOD_DATASET-SPLIT[-TYPE].csv``; the method name must not contain an
  underscore (the evaluation splits the name at underscores), e.g. ``dopehope-dr50_hope-test.csv``.
"""
from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.geometry import checked_rotation
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.jsonfields import read_text_file

HEADER = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
#: Two estimates of one image whose times differ by more than this (s) are rejected (BOP).
TIME_TOLERANCE_S = 0.001
_NAME_RE = re.compile(r"^(?P<method>[A-Za-z0-9-]+)_(?P<dataset>[a-z0-9]+)-(?P<split>[a-z]+)"
                      r"(?:-(?P<split_type>[a-z0-9]+))?\.csv$")
_METHOD_RE = re.compile(r"^[A-Za-z0-9-]+$")


@dataclass
class BopEstimate:
    """One pose estimate of a BOP19 submission.

    Attributes:
        scene_id, im_id, obj_id: BOP identifiers.
        score: confidence (higher is better).
        R: (3, 3) rotation, model -> camera.
        t: (3,) translation, metres.
        time: seconds for the whole image, or -1 when unknown.
        t_mm: (3,) translation in millimetres as read from a file (None when built in memory:
            then ``1000 * t``).
        line: line number in the file read (0 when built in memory).
    """

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0
    t_mm: np.ndarray | None = None
    line: int = 0


def bop_result_filename(method: str, dataset: str = "hope", split: str = "test",
                        split_type: str | None = None) -> str:
    """``METHOD_DATASET-SPLIT[-TYPE].csv``; raises ValueError for a method with an underscore."""
    if not _METHOD_RE.match(method):
        raise ValueError(f"BOP method name {method!r} may contain only letters, digits and '-' "
                         f"(no underscore: BOP splits the file name at '_')")
    name = f"{method}_{dataset}-{split}" + (f"-{split_type}" if split_type else "") + ".csv"
    parse_bop_result_filename(name)
    return name


def parse_bop_result_filename(path: str | os.PathLike) -> tuple[str, str, str, str | None]:
    """(method, dataset, split, split_type) of a BOP result file name.

    Raises:
        InputFileError: the name is not ``METHOD_DATASET-SPLIT[-TYPE].csv`` with an
        underscore-free method name.
    """
    name = Path(path).name
    m = _NAME_RE.match(name)
    if m is None:
        raise InputFileError(path, "BOP result files must be named METHOD_DATASET-SPLIT.csv with no "
                                   "underscore in METHOD (e.g. mymethod_hope-test.csv)")
    return m["method"], m["dataset"], m["split"], m["split_type"]


def _check_times(estimates: list[BopEstimate], path: str | os.PathLike) -> None:
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (e.scene_id, e.im_id)
        if key in times and abs(times[key] - e.time) > TIME_TOLERANCE_S:
            raise InputFileError(path, f"scene {e.scene_id} image {e.im_id}: estimates have different "
                                       f"times ({times[key]} s vs {e.time} s); BOP needs one time per image")
        times.setdefault(key, e.time)


def _fmt(x: float) -> str:
    return repr(float(x))


def write_bop_csv(path: str | os.PathLike, estimates: list[BopEstimate],
                  overwrite: bool = False) -> Path:
    """Write a BOP19 submission atomically.

    Args:
        path: ``.../METHOD_hope-test.csv`` (the name is validated).
        estimates: the pose estimates (translation in metres; written in millimetres).
        overwrite: replace an existing file (refused otherwise).

    Returns:
        The path written.

    Raises:
        InputFileError: bad file name, an existing file without ``overwrite``, non-finite
        numbers, or two estimates of one image with different times.
    """
    path = Path(path)
    parse_bop_result_filename(path)
    if path.exists() and not overwrite:
        raise InputFileError(path, "file exists; pass overwrite=True (--overwrite) to replace it")
    _check_times(estimates, path)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(HEADER)
    for k, e in enumerate(estimates):
        R = np.asarray(e.R, dtype=np.float64).reshape(3, 3)
        t_mm = 1000.0 * np.asarray(e.t, dtype=np.float64).reshape(3)
        values = [e.score, e.time, *R.ravel(), *t_mm]
        if not all(math.isfinite(v) for v in values):
            raise InputFileError(path, f"estimate {k} (scene {e.scene_id}, image {e.im_id}, object "
                                       f"{e.obj_id}) has a non-finite number")
        writer.writerow([int(e.scene_id), int(e.im_id), int(e.obj_id), _fmt(e.score),
                         " ".join(_fmt(v) for v in R.ravel()), " ".join(_fmt(v) for v in t_mm),
                         _fmt(e.time)])
    atomic_write_text(path, buf.getvalue())
    return path


def read_bop_csv(path: str | os.PathLike, check_name: bool = False) -> list[BopEstimate]:
    """Read a BOP19 submission (translation converted to metres).

    Args:
        path: the CSV file.
        check_name: also require the ``METHOD_DATASET-SPLIT.csv`` naming.

    Raises:
        InputFileError: missing file, wrong header, or a malformed line (named by number),
        e.g. an R that is no rotation.
    """
    path = Path(path)
    if check_name:
        parse_bop_result_filename(path)
    text = read_text_file(path, "BOP result file")
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(c.strip() for c in rows[0]) != HEADER:
        raise InputFileError(path, f"line 1: expected the header {','.join(HEADER)}")
    out = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(HEADER):
            raise InputFileError(path, f"line {lineno}: expected {len(HEADER)} fields, got {len(row)}")
        try:
            scene_id, im_id, obj_id = (int(row[i]) for i in range(3))
            score = float(row[3])
            R = np.array([float(v) for v in row[4].split()], dtype=np.float64)
            t = np.array([float(v) for v in row[5].split()], dtype=np.float64)
            time = float(row[6])
        except ValueError as exc:
            raise InputFileError(path, f"line {lineno}: not a number ({exc})") from None
        if R.size != 9:
            raise InputFileError(path, f"line {lineno}: R needs 9 numbers, got {R.size}")
        if t.size != 3:
            raise InputFileError(path, f"line {lineno}: t needs 3 numbers, got {t.size}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and math.isfinite(score)):
            raise InputFileError(path, f"line {lineno}: contains NaN or infinity")
        R = R.reshape(3, 3)
        try:
            checked_rotation(R)
        except ValueError as exc:
            raise InputFileError(path, f"line {lineno}: R: {exc}") from None
        out.append(BopEstimate(scene_id, im_id, obj_id, score, R, 0.001 * t, time, t_mm=t,
                               line=lineno))
    _check_times(out, path)
    return out
