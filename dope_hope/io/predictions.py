"""Pose predictions files: JSON lines written by ``dope-hope infer``, read by ``dope-hope evaluate``.

One detection per line (UTF-8, one JSON object per line; blank lines and lines starting with
``#`` are skipped)::

    {"image": "000123.png", "class": "Ketchup", "score": 0.93,
     "R": [[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]],
     "t": [0.012, -0.034, 0.651],
     "ls_applied": true}

* ``image`` — the image the detection belongs to: its path relative to the dataset folder
  (``scene_0001/0005_rgb.jpg``), an absolute path, or just the file name / stem
  (``000123.png`` / ``000123``) when that is unique in the dataset.
* ``class`` — HOPE object name (``"Ketchup"``, as in :mod:`dope_hope.catalog`); a BOP
  ``obj_id`` (int) may be given instead.
* ``score`` — detection confidence, higher is better (used to rank detections).
* ``R`` — (3, 3) rotation, model (mesh frame) -> camera, nested rows or 9 numbers
  row-major; or instead ``quaternion_xyzw`` [x, y, z, w] of that rotation.
* ``t`` — (3,) translation in **metres**, OpenCV camera frame: ``x_c = R x + t``.
* optional: ``ls_applied`` (bool, the depth line search refined ``t``), ``time`` (seconds for
  the whole image), ``scene_id`` / ``im_id`` (BOP ids, an alternative to ``image``); any
  other key (keypoints, reprojection error, ...) is ignored. Tracked streams (``dope-hope
  infer --track``) write the tracked pose as ``R`` / ``t`` (what is scored) and add
  ``R_detected`` / ``t_detected`` (the frame's own estimate, null when coasted),
  ``track_id`` and ``tracked`` ("detected" | "coasted").

An optional first line ``{"format": "dope-hope-predictions", "method": "NAME", ...}`` carries
metadata. A BOP19 submission CSV (:mod:`dope_hope.io.bop_csv`) is read as well.

**Official DOPE inference output** (NVlabs/Deep_Object_Pose ``inference/inference.py``): a
folder (``OUTF/<weights name>``) with one ``<image stem>.json`` per image, in the images'
sub-folders: ``{"camera_data": {}, "objects": [{"class", "location" (3, cm),
"quaternion_xyzw" (4,), "projected_cuboid"}]}``. ``location`` / ``quaternion_xyzw`` are the
official DOPE cuboid's pose (its frame, its centre; ``x_c = R p + t``). Each object becomes a
prediction of the image with that relative path (suffix dropped), its pose of the cuboid
*centre* (``origin == "cuboid"``: the evaluation moves ``t`` to the mesh origin) with
``R`` converted to the mesh frame by ``official_frame``: "legacy" (the official HOPE weights
and networks trained on NViSII data: ``R L^T``, the rotation NVlabs ``evaluate/evaluate.py``
applies to every prediction) or "cuboid" (the cuboid frame is the mesh frame, e.g. YCB
weights scored on NDDS/FAT ground truth). The files carry no score: 1.0 unless an object has
``score`` or ``confidence``; equal scores are ranked in file order.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError, DopeHopeError, InputFileError, UnknownObjectError
from dope_hope.geometry import ROTATION_TOLERANCE, checked_rotation, legacy_rotation_to_mesh, quaternion_xyzw_to_matrix
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.bop_csv import parse_bop_result_filename, read_bop_csv
from dope_hope.io.jsonfields import JsonFields, load_json_object, read_text_file

FORMAT_NAME = "dope-hope-predictions"
#: How the official DOPE inference's cuboid frame relates to the mesh frame.
OFFICIAL_FRAMES = ("legacy", "cuboid")
@dataclass
class Prediction:
    """One detection with its 6-DoF pose.

    Attributes:
        image: image reference as written in the file (None for BOP CSV rows).
        class_name: object class.
        score: confidence.
        R: (3, 3) rotation; t: (3,) metres.
        ls_applied: whether the depth line search refined t (None: not recorded).
        time: seconds for the whole image, or None.
        scene_id, im_id: BOP ids, or None.
        line: line number in the file (for messages).
        stored_pose: (R (3, 3), t (3,) millimetres) exactly as a BOP CSV row writes them, or
            None (JSON lines); BOP19 scoring uses it (see ``ObjectAnnotation.stored_pose``).
        origin: "mesh" (t places the mesh origin) or "cuboid" (t places the centre of the
            object's bounding box: official DOPE output).
    """

    image: str | None
    class_name: str
    score: float
    R: np.ndarray
    t: np.ndarray
    ls_applied: bool | None = None
    time: float | None = None
    scene_id: int | None = None
    im_id: int | None = None
    line: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    stored_pose: tuple[np.ndarray, np.ndarray] | None = None
    origin: str = "mesh"


def prediction_record(image: str, class_name: str, score: float, R: np.ndarray, t: np.ndarray,
                      ls_applied: bool | None = None, **extra: Any) -> dict[str, Any]:
    """The JSON object of one detection (see the module docstring); ``extra`` keys are kept."""
    rec: dict[str, Any] = {
        "image": str(image), "class": str(class_name), "score": float(score),
        "R": np.asarray(R, dtype=np.float64).reshape(3, 3).tolist(),
        "t": [float(v) for v in np.asarray(t, dtype=np.float64).reshape(3)],
    }
    if ls_applied is not None:
        rec["ls_applied"] = bool(ls_applied)
    for k, v in extra.items():
        rec[k] = v.tolist() if isinstance(v, np.ndarray) else v
    return rec


def write_predictions_jsonl(path: str | os.PathLike, records: list[dict[str, Any]],
                            method: str | None = None) -> None:
    """Write detections (dicts from :func:`prediction_record`) as JSON lines, atomically."""
    lines = []
    if method is not None:
        lines.append(json.dumps({"format": FORMAT_NAME, "method": method}))
    lines += [json.dumps(r) for r in records]
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


def _fail(path: Path, lineno: int, problem: str) -> InputFileError:
    return InputFileError(path, f"line {lineno}: {problem}")


def _rotation(path: Path, lineno: int, obj: dict) -> np.ndarray:
    """R, or the quaternion's rotation; a record giving both must give the same rotation."""
    if obj.get("R") is not None and obj.get("quaternion_xyzw") is not None:
        R = _rotation(path, lineno, {"R": obj["R"]})
        Rq = _rotation(path, lineno, {"quaternion_xyzw": obj["quaternion_xyzw"]})
        if np.linalg.norm(R - Rq) > ROTATION_TOLERANCE:
            angle = np.degrees(np.arccos(np.clip((np.trace(R.T @ Rq) - 1) / 2, -1.0, 1.0)))
            raise _fail(path, lineno, f"R and quaternion_xyzw disagree (by {angle:.3g} deg); give one "
                                      "rotation, or the same one twice")
        return R
    if obj.get("R") is not None:
        try:
            M = np.asarray(obj["R"], dtype=np.float64)
        except (TypeError, ValueError):
            raise _fail(path, lineno, "R: expected numbers") from None
        if M.size != 9:
            raise _fail(path, lineno, f"R: expected 3x3 (or 9) numbers, got {M.size}")
        M = M.reshape(3, 3)
        if not np.all(np.isfinite(M)):
            raise _fail(path, lineno, "R: contains NaN or infinity")
        try:
            return checked_rotation(M)
        except ValueError as exc:
            raise _fail(path, lineno, f"R: {exc}") from None
    if obj.get("quaternion_xyzw") is not None:
        try:
            q = np.asarray(obj["quaternion_xyzw"], dtype=np.float64).reshape(4)
        except (TypeError, ValueError):
            raise _fail(path, lineno, "quaternion_xyzw: expected 4 numbers") from None
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-8:
            raise _fail(path, lineno, "quaternion_xyzw: zero, NaN or infinity")
        return quaternion_xyzw_to_matrix(q)
    raise _fail(path, lineno, "missing field 'R' (or 'quaternion_xyzw')")


def _class_name(path: Path, lineno: int, obj: dict) -> str:
    if isinstance(obj.get("class"), str) and obj["class"]:
        return obj["class"]
    if obj.get("obj_id") is not None:
        try:
            return get_object(int(obj["obj_id"])).name
        except (DopeHopeError, TypeError, ValueError) as exc:
            raise _fail(path, lineno, f"obj_id: {exc}") from None
    raise _fail(path, lineno, "missing field 'class' (a non-empty string) or 'obj_id'")


def _optional_int(path: Path, lineno: int, obj: dict, key: str) -> int | None:
    v = obj.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v):
        raise _fail(path, lineno, f"{key}: expected an integer, got {v!r}")
    return int(v)


def _parse_line(path: Path, lineno: int, obj: Any) -> Prediction:
    if not isinstance(obj, dict):
        raise _fail(path, lineno, f"expected a JSON object, got {type(obj).__name__}")
    image = obj.get("image")
    if image is not None and not isinstance(image, str):
        raise _fail(path, lineno, f"image: expected a string, got {image!r}")
    scene_id = _optional_int(path, lineno, obj, "scene_id")
    im_id = _optional_int(path, lineno, obj, "im_id")
    if image is None and (scene_id is None or im_id is None):
        raise _fail(path, lineno, "missing field 'image' (or both 'scene_id' and 'im_id')")
    score = obj.get("score")
    if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
        raise _fail(path, lineno, f"score: expected a finite number, got {score!r}")
    try:
        t = np.asarray(obj["t"], dtype=np.float64).reshape(3)
    except KeyError:
        raise _fail(path, lineno, "missing field 't' (translation, metres)") from None
    except (TypeError, ValueError):
        raise _fail(path, lineno, "t: expected 3 numbers (metres)") from None
    if not np.all(np.isfinite(t)):
        raise _fail(path, lineno, "t: contains NaN or infinity")
    ls = obj.get("ls_applied")
    if ls is not None and not isinstance(ls, bool):
        raise _fail(path, lineno, f"ls_applied: expected true/false, got {ls!r}")
    time = obj.get("time")
    if time is not None and (isinstance(time, bool) or not isinstance(time, (int, float))):
        raise _fail(path, lineno, f"time: expected seconds, got {time!r}")
    known = {"image", "class", "obj_id", "score", "R", "quaternion_xyzw", "t", "ls_applied",
             "time", "scene_id", "im_id"}
    return Prediction(image=image, class_name=_class_name(path, lineno, obj), score=float(score),
                      R=_rotation(path, lineno, obj), t=t, ls_applied=ls,
                      time=None if time is None else float(time), scene_id=scene_id, im_id=im_id,
                      line=lineno, extra={k: v for k, v in obj.items() if k not in known})


def read_predictions(path: str | os.PathLike,
                     official_frame: str = "legacy") -> tuple[list[Prediction], dict[str, Any]]:
    """Read predictions: JSON lines (above), a BOP19 CSV (``.csv``) or a folder of official
    DOPE inference output (``official_frame``: see the module docstring).

    Returns:
        (predictions, metadata); metadata holds the optional first-line keys (``method``),
        for a BOP CSV the method name parsed from the file name (when it follows the BOP
        naming), for an official folder its name.

    Raises:
        InputFileError: missing file or a malformed line (its number is in the message).
    """
    path = Path(path)
    if path.is_dir():
        return read_official_dope_output(path, official_frame)
    if path.suffix.lower() == ".csv":
        return _read_bop(path)
    text = read_text_file(path, "predictions file")
    preds: list[Prediction] = []
    meta: dict[str, Any] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            obj = json.loads(s)
        except json.JSONDecodeError as exc:
            raise _fail(path, lineno, f"malformed JSON ({exc.msg}); expected one object per line") from None
        if isinstance(obj, dict) and "format" in obj and "class" not in obj and "obj_id" not in obj:
            if obj["format"] != FORMAT_NAME:
                raise _fail(path, lineno, f"format: expected {FORMAT_NAME!r}, got {obj['format']!r}")
            meta.update(obj)
            continue
        preds.append(_parse_line(path, lineno, obj))
    return preds, meta


def _read_bop(path: Path) -> tuple[list[Prediction], dict[str, Any]]:
    meta: dict[str, Any] = {}
    try:
        meta["method"] = parse_bop_result_filename(path)[0]
    except InputFileError:
        pass
    preds = []
    for e in read_bop_csv(path):
        try:
            name = get_object(e.obj_id).name
        except DopeHopeError as exc:
            raise InputFileError(path, f"line {e.line}: {exc}") from None
        preds.append(Prediction(image=None, class_name=name, score=e.score, R=e.R, t=e.t,
                                time=None if e.time < 0 else e.time, scene_id=e.scene_id,
                                im_id=e.im_id, line=e.line, stored_pose=(e.R, e.t_mm)))
    return preds, meta


def read_official_dope_output(folder: str | os.PathLike,
                              official_frame: str = "legacy") -> tuple[list[Prediction], dict[str, Any]]:
    """The per-image JSON files of NVIDIA's DOPE inference (module docstring), as predictions.

    Raises:
        InputFileError: a folder without JSON files, or a malformed file (named, with field).
        ConfigError: an unknown ``official_frame``.
    """
    if official_frame not in OFFICIAL_FRAMES:
        raise ConfigError(f"official DOPE frame must be one of {', '.join(OFFICIAL_FRAMES)}, "
                          f"got {official_frame!r}")
    folder = Path(folder)
    files = sorted(p for p in folder.rglob("*.json") if p.is_file())
    if not files:
        raise InputFileError(folder, "no .json files (official DOPE inference output) in this folder")
    preds: list[Prediction] = []
    for path in files:
        f = JsonFields(path)
        objs = f.get(load_json_object(path, "DOPE inference output"), "objects", "")
        if not isinstance(objs, list):
            raise f.fail("objects", f"expected a list, got {type(objs).__name__}")
        image = path.relative_to(folder).with_suffix("").as_posix()
        for i, o in enumerate(objs):
            where = f"objects[{i}]"
            name = f.get(o, "class", where)
            if not isinstance(name, str) or not name:
                raise f.fail(f"{where}.class", f"expected a non-empty string, got {name!r}")
            try:
                name = get_object(name).name
            except UnknownObjectError:
                pass
            t = 0.01 * f.array(f.get(o, "location", where), f"{where}.location", (3,))
            q = f.array(f.get(o, "quaternion_xyzw", where), f"{where}.quaternion_xyzw", (4,))
            if np.linalg.norm(q) < 1e-8:
                raise f.fail(f"{where}.quaternion_xyzw", "zero quaternion")
            R = quaternion_xyzw_to_matrix(q)
            if official_frame == "legacy":
                R = legacy_rotation_to_mesh(R)
            score = 1.0
            for key in ("score", "confidence"):
                if o.get(key) is not None:
                    score = f.number(o[key], f"{where}.{key}")
                    break
            preds.append(Prediction(image=image, class_name=name, score=score, R=R, t=t, line=i + 1,
                                    origin="cuboid"))
    return preds, {"method": folder.name}
