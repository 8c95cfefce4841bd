"""Evaluation of 6-DoF predictions against a dataset: HOPE-paper tables, curves, BOP19 AR.

**Predictions file** (what ``dope-hope infer`` prints; reader and writer in
:mod:`dope_hope.io.predictions`): JSON lines, one detection per line::

    {"image": "000123.png", "class": "Ketchup", "score": 0.93,
     "R": [[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]], "t": [0.012, -0.034, 0.651],
     "ls_applied": true}

``image`` is the image path relative to the dataset folder (or absolute, or a file name /
stem that is unique in the dataset); ``class`` the HOPE object name (or ``obj_id``);
``score`` the confidence; ``R`` (3x3, model -> camera, or ``quaternion_xyzw``) and ``t``
(metres, OpenCV camera, ``x_c = R x + t``); optional ``ls_applied`` (depth line search
used), ``time`` (s per image), ``scene_id``/``im_id`` (BOP). An optional first line
``{"format": "dope-hope-predictions", "method": "NAME"}`` names the method. A BOP19
submission CSV (``METHOD_hope-test.csv``) is accepted too.

**HOPE-paper evaluation** (per image and object class): predictions are matched to ground
truth one-to-one, greedily in descending score, each taking the not-yet-matched GT instance of
least error, if that error is strictly below the threshold. Per object: diameter, mean GT
visibility, pixels (mean area of the GT 2D silhouette: convex hull of the projected model
points, occlusion ignored, px^2), distance (mean GT camera distance of the model origin),
the median error of the true positives at 10 cm, precision (TP / detections) and recall
(TP / GT instances) at 2 cm and 10 cm; category and overall rows are means over the objects
that have GT instances. Detection rate (recall) vs threshold 0.5 .. 10 cm is pooled over the
GT instances of a group (all, a category, an object). Errors are ADD-H by default (500 model
points); ``add``, ``adds``, ``meanssd``, ``mssd`` on request.

**BOP19 average recall** (as the BOP toolkit computes it, localization task): targets from
``test_targets_bop19.json`` when the dataset has one, else every (image, object) with GT
instances of visibility >= 0.1 (inst_count = their number; a missing visibility counts as
visible); for each target only the ``inst_count`` top-scoring estimates are evaluated and the
``inst_count`` most visible GT instances are the valid ones; greedy matching as above. A pose
is correct when its error is strictly below the threshold. AR_MSSD: thresholds 0.05 .. 0.5 of
the diameter, the error is infinite when ``|t_e - t_g| >= diameter`` (the toolkit's short-cut);
AR_MSPD: 5 .. 50 px scaled by 640 / image width; AR_VSD: delta 15 mm, tau 0.05 .. 0.5 of the
diameter, thresholds 0.05 .. 0.5 (VSD is 1 when the projections of the bounding spheres do not
overlap; needs test depth and meshes, skipped and reported so when a frame has no depth);
AR = mean of the three. Recall = true positives / valid GT instances, over all targets.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope import metrics
from dope_hope.annotation import ObjectAnnotation
from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
from dope_hope.io.atomic import atomic_path, atomic_write_text
from dope_hope.io.predictions import Prediction

#: Table metrics (all in metres). "addh" is the HOPE paper's.
METRICS = ("addh", "add", "adds", "meanssd", "mssd")
METRIC_LABELS = {"addh": "ADD-H", "add": "ADD", "adds": "ADD-S", "meanssd": "MeanSSD",
                 "mssd": "MSSD"}
DEFAULT_METRIC = "addh"
#: Precision/recall thresholds of the per-object table, metres.
TABLE_THRESHOLDS_M = (0.02, 0.10)
#: Detection-rate curve thresholds, 0.5 .. 10 cm, metres.
CURVE_THRESHOLDS_M = tuple(round(0.005 * k, 4) for k in range(1, 21))
#: Number of model points for the ADD family (the HOPE paper: 500).
NUM_MODEL_POINTS = 500
CATEGORY_ORDER = ("cylinder", "cuboid", "bottle")

VISIB_GT_MIN = 0.1
BOP19_MSSD_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))   # x diameter
BOP19_MSPD_THRESHOLDS = tuple(5.0 * k for k in range(1, 11))              # px at width 640
BOP19_VSD_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))
BOP19_MAX_SYM_DISC_STEP = 0.01


# =========================================================================== dataset
@dataclass
class EvalFrame:
    """One test image with its ground truth.

    Attributes:
        key: unique id: image path relative to the dataset folder (posix).
        K: (3, 3) intrinsics or None; width, height: pixels or None.
        objects: GT instances (metres, mesh frame).
        aliases: names a prediction may use for this image (relative paths, file name, stem).
        image_path, depth_path, depth_scale_m: files and the depth unit (metres per unit).
        scene_id, im_id: BOP ids when known.
    """

    key: str
    K: np.ndarray | None
    width: int | None
    height: int | None
    objects: list[ObjectAnnotation]
    aliases: set[str] = field(default_factory=set)
    image_path: Path | None = None
    depth_path: Path | None = None
    depth_scale_m: float = 0.001
    scene_id: int | None = None
    im_id: int | None = None


@dataclass
class Dataset:
    """Frames plus optional BOP targets {(scene_id, im_id, obj_id): inst_count}."""

    root: Path
    fmt: str
    frames: list[EvalFrame]
    targets: dict[tuple[int, int, int], int] | None = None


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
    return EvalFrame(key=key, K=ann.K, width=ann.width, height=ann.height,
                     objects=list(ann.objects), aliases=_aliases(root, image, json_path),
                     image_path=image, depth_path=ann.depth_path, depth_scale_m=ann.depth_scale_m)


def load_dataset(root: str | os.PathLike, fmt: str = "dope") -> Dataset:
    """Read the ground truth of a test set.

    Args:
        root: dataset folder (searched recursively for DOPE / HOPE frames).
        fmt: "dope" (``dope_hope.io.dope_json``), "hope" (``io.hope_json``) or "bop"
            (``io.bop``, a BOP split folder or a dataset folder with ``test/``).

    Raises:
        InputFileError: no frames found or a malformed annotation.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputFileError(root, "dataset folder not found")
    if fmt == "dope":
        from dope_hope.io.dope_json import list_dope_frames, read_dope_json

        frames = [_frame_from_annotation(root, read_dope_json(p), p)
                  for d in _subfolders(root) for p in list_dope_frames(d)]
        ds = Dataset(root, fmt, frames)
    elif fmt == "hope":
        from dope_hope.io.hope_json import list_hope_frames, read_hope_json

        frames = [_frame_from_annotation(root, read_hope_json(p), p)
                  for d in _subfolders(root) for p in list_hope_frames(d)]
        ds = Dataset(root, fmt, frames)
    elif fmt == "bop":
        ds = _load_bop(root)
    else:
        raise ConfigError(f"unknown dataset format {fmt!r}; use dope, hope or bop")
    if not ds.frames:
        raise InputFileError(root, f"no {fmt}-format frames found (annotation + image pairs)")
    return ds


def _load_bop(root: Path) -> Dataset:
    """A BOP split folder (``<split>/<scene_id>/scene_gt.json`` ...) or a dataset folder with
    a ``test/`` split, through :mod:`dope_hope.io.bop`; targets from
    ``test_targets_bop19.json`` in the split or dataset folder when present."""
    from dope_hope.io import bop as bop_io

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
            key=key, K=ann.K, width=ann.width, height=ann.height, objects=list(ann.objects),
            aliases=_aliases(split_dir, ann.image_path) | {ids},
            image_path=ann.image_path, depth_path=ann.depth_path,
            depth_scale_m=ann.depth_scale_m, scene_id=bf.scene_id, im_id=bf.im_id))
    targets = None
    for candidate in (split_dir / "test_targets_bop19.json", split_dir.parent / "test_targets_bop19.json"):
        if candidate.is_file():
            targets = {(s, i, o): n for s, i, o, n in bop_io.read_test_targets(candidate)}
            break
    return Dataset(split_dir, "bop", frames, targets)


# =========================================================================== predictions
def assign_predictions(dataset: Dataset, preds: list[Prediction],
                       source: str | os.PathLike = "predictions") -> list[list[Prediction]]:
    """Group predictions by dataset frame (index-aligned with ``dataset.frames``).

    A prediction's ``image`` is matched against each frame's aliases (relative path, path
    without suffix, file name, stem, absolute path); BOP rows by (scene_id, im_id).

    Raises:
        InputFileError: an image that is not in the dataset, or a name shared by two frames.
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
        if idx is None:
            what = repr(p.image) if p.image is not None else f"scene {p.scene_id} image {p.im_id}"
            raise InputFileError(source, f"line {p.line}: image {what} is not in the dataset "
                                         f"{dataset.root} ({dataset.fmt} format)")
        out[idx].append(p)
    return out


# =========================================================================== object models
@dataclass
class ObjectModel:
    """What the metrics need of one object.

    Attributes:
        name, obj_id, category: identity ("other" for a class outside the catalog).
        points: (N, 3) model points, metres.
        diameter: metres.
        symmetries: (S, 4, 4) model-frame symmetry transforms, metres, identity first.
        mesh: trimesh in metres (for VSD), or None.
        source: where points / mesh come from, for the report.
        procedural: True when the points are sampled on the catalog cuboid (no mesh given).
    """

    name: str
    obj_id: int | None
    category: str
    points: np.ndarray
    diameter: float
    symmetries: np.ndarray
    mesh: Any = None
    source: str = ""
    procedural: bool = False


def _centred_symmetries(syms: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Symmetries about ``center`` instead of the origin: ``T(c) S T(-c)``."""
    if np.allclose(center, 0.0, atol=1e-6):
        return syms
    T = np.eye(4)
    T[:3, 3] = center
    Ti = np.eye(4)
    Ti[:3, 3] = -center
    return np.einsum("ij,sjk,kl->sil", T, syms, Ti)


def _catalog_entry(name: str):
    from dope_hope.catalog import get_object

    try:
        return get_object(name)
    except UnknownObjectError:
        return None


def parse_mesh_args(mesh_args: Sequence[str]) -> dict[str | None, Path]:
    """``--mesh [NAME=]PATH`` values -> {class name or None: path}.

    Without ``NAME=``, the class is the catalog object named by the file stem or by its
    folder (``Ketchup.obj``, ``Ketchup/textured.obj``); None if neither names one.
    """
    out: dict[str | None, Path] = {}
    for arg in mesh_args:
        if "=" in arg and not Path(arg).exists():
            name, path = arg.split("=", 1)
            obj = _catalog_entry(name)
            out[obj.name if obj else name] = Path(path)
            continue
        p = Path(arg)
        obj = _catalog_entry(p.stem) or _catalog_entry(p.parent.name)
        out[obj.name if obj else None] = p
    return out


def load_models(class_names: Sequence[str], mesh_args: Sequence[str] = (),
                models_dir: str | os.PathLike | None = None, mesh_units: str | None = None,
                n_points: int = NUM_MODEL_POINTS, cyl_step_deg: float = 1.0) -> dict[str, ObjectModel]:
    """Model points, diameter and symmetries of every class.

    Sources, in order: ``--mesh`` files; ``--models-dir`` (BOP ``models_info.json`` +
    ``obj_XXXXXX.ply`` in mm, or HOPE ``<Name>/textured.obj`` / ``<Name>.obj`` in cm); else a
    **procedural** stand-in: points on the surface of the catalog cuboid (reported as such).
    Symmetries: BOP ``models_info`` when used (discretized as the toolkit does), else the
    catalog category's (cylinders in ``cyl_step_deg`` steps) about the mesh's box centre.

    Raises:
        InputFileError / UnknownObjectError: unreadable mesh; a class neither in the catalog
        nor given a mesh.
    """
    import trimesh

    from dope_hope.catalog import category_symmetries
    from dope_hope.io.meshes import load_mesh, mesh_cuboid, mesh_diameter, sample_surface_points

    meshes = parse_mesh_args(mesh_args)
    if None in meshes:
        if len(class_names) == 1 and len(meshes) == 1:
            meshes = {class_names[0]: meshes[None]}
        else:
            raise ConfigError(f"--mesh {meshes[None]}: cannot tell which object it is; "
                              f"write --mesh NAME=PATH (classes: {', '.join(class_names)})")
    models_info: dict[int, dict] = {}
    mdir = Path(models_dir) if models_dir is not None else None
    if mdir is not None:
        if not mdir.is_dir():
            raise InputFileError(mdir, "models folder not found")
        info_path = mdir / "models_info.json"
        if info_path.is_file():
            try:
                models_info = {int(k): v for k, v in
                               json.loads(info_path.read_text(encoding="utf-8")).items()}
            except (ValueError, json.JSONDecodeError, AttributeError) as exc:
                raise InputFileError(info_path, f"malformed models_info.json ({exc})") from None
    out: dict[str, ObjectModel] = {}
    for name in class_names:
        obj = _catalog_entry(name)
        category = obj.category if obj else "other"
        obj_id = obj.obj_id if obj else None
        mesh, source, info = None, "", None
        if name in meshes:
            mesh = load_mesh(meshes[name], units=mesh_units)
            source = f"mesh {meshes[name]}"
        elif mdir is not None:
            candidates = []
            if obj_id is not None:
                candidates.append(mdir / f"obj_{obj_id:06d}.ply")
            candidates += [mdir / name / "textured.obj", mdir / f"{name}.obj", mdir / f"{name}.ply"]
            path = next((c for c in candidates if c.is_file()), None)
            if path is not None:
                mesh = load_mesh(path, units=mesh_units)
                source = f"mesh {path}"
                if path.suffix.lower() == ".ply" and obj_id in models_info:
                    info = models_info[obj_id]
                    source += " + models_info.json"
        if mesh is None:
            if obj is None:
                raise UnknownObjectError(f"class {name!r} is not a HOPE object and no mesh was "
                                         f"given for it (--mesh {name}=PATH)")
            mesh = trimesh.creation.box(extents=obj.size_array)
            source = "procedural cuboid (catalog size; no mesh given)"
        points = sample_surface_points(mesh, n_points)
        if info is not None:
            syms = metrics.symmetries_from_models_info(info, BOP19_MAX_SYM_DISC_STEP)
            diameter = 0.001 * float(info["diameter"]) if "diameter" in info else mesh_diameter(mesh)
        else:
            syms = (category_symmetries(category, step_deg=cyl_step_deg) if obj else np.eye(4)[None])
            syms = _centred_symmetries(syms, mesh_cuboid(mesh)[1])
            diameter = mesh_diameter(mesh)
        out[name] = ObjectModel(name=name, obj_id=obj_id, category=category, points=points,
                                diameter=diameter, symmetries=syms, mesh=mesh, source=source,
                                procedural=source.startswith("procedural"))
    return out


# =========================================================================== errors + matching
def pose_error(metric: str, pred_R: np.ndarray, pred_t: np.ndarray, gt: ObjectAnnotation,
               model: ObjectModel, upper: float | None = None) -> float:
    """Error of one estimate against one GT instance, metres (``METRICS``)."""
    args = (pred_R, pred_t, gt.R, gt.t)
    if metric == "addh":
        return metrics.addh(*args, model.points, upper=upper)
    if metric == "add":
        return metrics.add(*args, model.points)
    if metric == "adds":
        return metrics.adds(*args, model.points)
    if metric == "meanssd":
        return metrics.mean_ssd(*args, model.points, model.symmetries)
    if metric == "mssd":
        return metrics.mssd(*args, model.points, model.symmetries)
    raise ConfigError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")


def greedy_match(errors: np.ndarray, scores: np.ndarray, threshold: float,
                 valid: np.ndarray | None = None) -> np.ndarray:
    """One-to-one greedy matching of estimates to GT instances (BOP ``match_poses``).

    Estimates are taken in descending score (ties: file order); each is matched to the valid,
    not yet matched GT instance of least error, if that error is strictly below
    ``threshold`` (ties: the first GT).

    Args:
        errors: (P, G) errors; scores: (P,); threshold: same unit as errors;
        valid: (G,) bool, GT instances that may be matched (default: all).

    Returns:
        (P,) int: the matched GT index, or -1.
    """
    errors = np.asarray(errors, dtype=np.float64)
    P, G = errors.shape
    match = np.full(P, -1, dtype=np.int64)
    if G == 0:
        return match
    taken = np.zeros(G, dtype=bool) if valid is None else ~np.asarray(valid, dtype=bool)
    for p in np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable"):
        e = np.where(taken, np.inf, errors[p])
        g = int(np.argmin(e))
        if e[g] < threshold:
            match[p] = g
            taken[g] = True
    return match


@dataclass
class GroupErrors:
    """Errors of the predictions of one class in one image against its GT instances."""

    frame: int
    class_name: str
    scores: np.ndarray                       # (P,)
    gt: list[ObjectAnnotation]               # G instances
    errors: dict[str, np.ndarray]            # metric -> (P, G) metres


def compute_errors(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                   models: dict[str, ObjectModel], metric_names: Sequence[str],
                   upper: float | None = max(CURVE_THRESHOLDS_M),
                   progress: bool = False) -> list[GroupErrors]:
    """Error matrices for every (image, class) that has GT instances or predictions.

    ADD-H values above ``upper`` may be returned as a lower bound (>= ``upper``), which
    never changes a match at thresholds <= ``upper``.
    """
    from tqdm import tqdm

    groups = []
    for fi in tqdm(range(len(dataset.frames)), desc="errors", unit="img", disable=not progress):
        frame = dataset.frames[fi]
        classes = sorted({o.class_name for o in frame.objects} |
                         {p.class_name for p in preds_by_frame[fi]})
        for c in classes:
            gts = [o for o in frame.objects if o.class_name == c]
            ps = [p for p in preds_by_frame[fi] if p.class_name == c]
            errs = {}
            for m in metric_names:
                E = np.empty((len(ps), len(gts)))
                for i, p in enumerate(ps):
                    for j, g in enumerate(gts):
                        E[i, j] = pose_error(m, p.R, p.t, g, models[c], upper=upper)
                errs[m] = E
            groups.append(GroupErrors(fi, c, np.array([p.score for p in ps], dtype=np.float64),
                                      gts, errs))
    return groups


# =========================================================================== HOPE tables
def _pixels(gt: ObjectAnnotation, model: ObjectModel, K: np.ndarray | None) -> float:
    """Area (px^2) of the convex hull of the projected model points; NaN if unknown."""
    if K is None:
        return math.nan
    from scipy.spatial import ConvexHull, QhullError

    cam = model.points @ np.asarray(gt.R).T + np.asarray(gt.t).reshape(3)
    if np.any(cam[:, 2] <= 0):
        return math.nan
    uv = cam @ np.asarray(K).T
    uv = uv[:, :2] / uv[:, 2:3]
    try:
        return float(ConvexHull(uv).volume)  # in 2D, "volume" is the area
    except (QhullError, ValueError):
        return 0.0


@dataclass
class ObjectRow:
    """One row of the per-object table (units in the field names)."""

    name: str
    category: str
    n_gt: int
    n_pred: int
    diameter_cm: float
    visibility: float
    pixels: float
    distance_cm: float
    median_tp_error_cm: float
    precision: dict[float, float]
    recall: dict[float, float]
    tp: dict[float, int]


def _nanmean(values: Sequence[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else math.nan


def _matched_errors(groups: list[GroupErrors], metric: str, threshold: float) -> dict[str, list[float]]:
    """Class -> errors of the true positives at ``threshold``."""
    out: dict[str, list[float]] = {}
    for g in groups:
        E = g.errors[metric]
        m = greedy_match(E, g.scores, threshold)
        out.setdefault(g.class_name, []).extend(float(E[i, j]) for i, j in enumerate(m) if j >= 0)
    return out


def object_table(dataset: Dataset, groups: list[GroupErrors], models: dict[str, ObjectModel],
                 metric: str, thresholds: Sequence[float] = TABLE_THRESHOLDS_M) -> list[ObjectRow]:
    """Per-object rows (objects with GT or predictions), ordered by category then name."""
    n_gt: dict[str, int] = {}
    n_pred: dict[str, int] = {}
    stats: dict[str, dict[str, list[float]]] = {}
    for g in groups:
        n_gt[g.class_name] = n_gt.get(g.class_name, 0) + len(g.gt)
        n_pred[g.class_name] = n_pred.get(g.class_name, 0) + len(g.scores)
        s = stats.setdefault(g.class_name, {"vis": [], "pix": [], "dist": []})
        K = dataset.frames[g.frame].K
        for o in g.gt:
            s["vis"].append(math.nan if o.visibility is None else float(o.visibility))
            s["pix"].append(_pixels(o, models[g.class_name], K))
            s["dist"].append(float(np.linalg.norm(o.t)))
    tps = {th: _matched_errors(groups, metric, th) for th in thresholds}
    med_th = max(thresholds)
    rows = []
    for name in n_gt:
        model = models[name]
        prec, rec, tp = {}, {}, {}
        for th in thresholds:
            k = len(tps[th].get(name, []))
            tp[th] = k
            prec[th] = k / n_pred[name] if n_pred[name] else math.nan
            rec[th] = k / n_gt[name] if n_gt[name] else math.nan
        med = tps[med_th].get(name, [])
        rows.append(ObjectRow(
            name=name, category=model.category, n_gt=n_gt[name], n_pred=n_pred[name],
            diameter_cm=100.0 * model.diameter, visibility=_nanmean(stats[name]["vis"]),
            pixels=_nanmean(stats[name]["pix"]), distance_cm=100.0 * _nanmean(stats[name]["dist"]),
            median_tp_error_cm=100.0 * float(np.median(med)) if med else math.nan,
            precision=prec, recall=rec, tp=tp))
    order = {c: i for i, c in enumerate(CATEGORY_ORDER)}
    rows.sort(key=lambda r: (order.get(r.category, len(order)), r.name))
    return rows


def summary_rows(rows: list[ObjectRow]) -> list[tuple[str, ObjectRow]]:
    """Category means and the overall mean over objects with GT instances."""
    out = []
    groups = [(c, [r for r in rows if r.category == c and r.n_gt > 0]) for c in CATEGORY_ORDER]
    groups.append(("overall", [r for r in rows if r.n_gt > 0]))
    for label, rs in groups:
        if not rs:
            continue
        ths = rs[0].precision.keys()
        out.append((label, ObjectRow(
            name=label, category=label, n_gt=sum(r.n_gt for r in rs), n_pred=sum(r.n_pred for r in rs),
            diameter_cm=_nanmean([r.diameter_cm for r in rs]),
            visibility=_nanmean([r.visibility for r in rs]), pixels=_nanmean([r.pixels for r in rs]),
            distance_cm=_nanmean([r.distance_cm for r in rs]),
            median_tp_error_cm=_nanmean([r.median_tp_error_cm for r in rs]),
            precision={t: _nanmean([r.precision[t] for r in rs]) for t in ths},
            recall={t: _nanmean([r.recall[t] for r in rs]) for t in ths},
            tp={t: sum(r.tp[t] for r in rs) for t in ths})))
    return out


def _f(v: float, digits: int = 2) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _th_label(th: float) -> str:
    return f"{100 * th:g}cm"


def table_markdown(rows: list[ObjectRow], title: str, notes: Sequence[str],
                   bop: dict[str, Any] | None = None) -> str:
    """The per-object table with category and overall rows, as Markdown."""
    ths = list(rows[0].precision) if rows else list(TABLE_THRESHOLDS_M)
    head = ["object", "category", "GT", "det.", "diam. (cm)", "visib.", "pixels", "dist. (cm)",
            f"median TP error @{_th_label(max(ths))} (cm)"]
    for th in ths:
        head += [f"P@{_th_label(th)}", f"R@{_th_label(th)}"]
    lines = [f"# {title}", ""] + [f"- {n}" for n in notes] + ["", "| " + " | ".join(head) + " |",
                                                             "|" + "---|" * len(head)]

    def cells(r: ObjectRow, bold: bool) -> list[str]:
        name = f"**{r.name}**" if bold else r.name
        c = [name, r.category if not bold else "", str(r.n_gt), str(r.n_pred), _f(r.diameter_cm, 1),
             _f(r.visibility), _f(r.pixels, 0), _f(r.distance_cm, 1), _f(r.median_tp_error_cm)]
        for th in ths:
            c += [_f(r.precision[th], 3), _f(r.recall[th], 3)]
        return c

    for r in rows:
        lines.append("| " + " | ".join(cells(r, False)) + " |")
    for label, r in summary_rows(rows):
        r.name = f"{label} (mean of objects)" if label != "overall" else "overall (mean of objects)"
        lines.append("| " + " | ".join(cells(r, True)) + " |")
    lines += ["", "pixels: mean area of the GT 2D silhouette (convex hull of the projected model "
                  "points, occlusion ignored), px². dist.: mean camera distance of the GT model "
                  "origin. visib.: mean GT visible fraction (– when the dataset has none). "
                  "Category/overall rows: means over the objects with GT instances."]
    if bop is not None:
        lines += ["", "## BOP19 average recall", "", "| AR | AR_VSD | AR_MSSD | AR_MSPD |",
                  "|---|---|---|---|",
                  "| " + " | ".join(_f(bop.get(k), 3) if bop.get(k) is not None else "skipped"
                                    for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd")) + " |", ""]
        lines += [f"- {n}" for n in bop.get("notes", [])]
    return "\n".join(lines) + "\n"


def table_csv(rows: list[ObjectRow]) -> str:
    """The per-object table (plus category/overall rows) as CSV, plain numbers."""
    ths = list(rows[0].precision) if rows else list(TABLE_THRESHOLDS_M)
    head = ["row", "object", "category", "gt", "detections", "diameter_cm", "visibility",
            "pixels_area_px2", "distance_cm", "median_tp_error_cm"]
    for th in ths:
        head += [f"precision_{_th_label(th)}", f"recall_{_th_label(th)}", f"tp_{_th_label(th)}"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)

    def num(v: float) -> str:
        return "" if v is None or (isinstance(v, float) and math.isnan(v)) else repr(float(v))

    for kind, r in [("object", r) for r in rows] + [("mean", r) for _, r in summary_rows(rows)]:
        vals = [kind, r.name, r.category, r.n_gt, r.n_pred, num(r.diameter_cm), num(r.visibility),
                num(r.pixels), num(r.distance_cm), num(r.median_tp_error_cm)]
        for th in ths:
            vals += [num(r.precision[th]), num(r.recall[th]), r.tp[th]]
        w.writerow(vals)
    return buf.getvalue()


# =========================================================================== curves
def detection_rates(groups: list[GroupErrors], models: dict[str, ObjectModel], metric: str,
                    thresholds: Sequence[float] = CURVE_THRESHOLDS_M) -> dict[str, dict[str, Any]]:
    """{group: {"gt": n, "tp": [..], "rate": [..]}} for "overall", each category and object.

    The rate at a threshold is the fraction of GT instances matched with an error below it
    (pooled over the group's instances).
    """
    out: dict[str, dict[str, Any]] = {}

    def bucket(name: str) -> dict[str, Any]:
        return out.setdefault(name, {"gt": 0, "tp": [0] * len(thresholds)})

    for g in groups:
        cat = models[g.class_name].category
        for name in ("overall", cat, g.class_name):
            bucket(name)["gt"] += len(g.gt)
        for k, th in enumerate(thresholds):
            n = int(np.count_nonzero(greedy_match(g.errors[metric], g.scores, th) >= 0))
            for name in ("overall", cat, g.class_name):
                bucket(name)["tp"][k] += n
    for b in out.values():
        b["rate"] = [t / b["gt"] if b["gt"] else math.nan for t in b["tp"]]
    return out


def write_curves(out_dir: Path, curves: dict[tuple[str, str], dict[str, dict[str, Any]]],
                 models: dict[str, ObjectModel],
                 thresholds: Sequence[float] = CURVE_THRESHOLDS_M) -> tuple[Path, Path]:
    """``detection_rate.csv`` (every group) and ``detection_rate.png`` (overall + categories).

    Args:
        curves: {(method, metric): detection_rates(...)}.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "metric", "group", "threshold_cm", "detection_rate", "true_positives",
                "gt_instances"])
    for (method, metric), groups in curves.items():
        for gname, b in groups.items():
            for k, th in enumerate(thresholds):
                rate = b["rate"][k]
                w.writerow([method, metric, gname, f"{100 * th:g}", "" if math.isnan(rate) else repr(rate),
                            b["tp"][k], b["gt"]])
    csv_path = out_dir / "detection_rate.csv"
    atomic_write_text(csv_path, buf.getvalue())

    panels = ["overall"] + [c for c in CATEGORY_ORDER
                            if any(c in g and g[c]["gt"] > 0 for g in curves.values())]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False)
    x = [100 * th for th in thresholds]
    metrics_used = {m for _, m in curves}
    method_color = {m: f"C{i % 10}" for i, m in enumerate(dict.fromkeys(m for m, _ in curves))}
    metric_style = {m: ("-", "--", ":", "-.", (0, (5, 1)))[i % 5]
                    for i, m in enumerate(dict.fromkeys(m for _, m in curves))}
    for ax, panel in zip(axes[0], panels):
        for (method, metric), groups in curves.items():
            if panel in groups and groups[panel]["gt"] > 0:
                label = method if len(metrics_used) == 1 else f"{method} ({METRIC_LABELS[metric]})"
                ax.plot(x, groups[panel]["rate"], marker=".", label=label, color=method_color[method],
                        linestyle=metric_style[metric])
        n = max((g[panel]["gt"] for g in curves.values() if panel in g), default=0)
        ax.set_title(f"{panel} ({n} GT)")
        ax.set_xlabel("threshold (cm)")
        ax.set_xlim(0, max(x))
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("detection rate")
    axes[0][0].legend(loc="lower right", fontsize="small")
    if len(metrics_used) == 1:
        fig.suptitle(f"detection rate vs {METRIC_LABELS[next(iter(metrics_used))]} threshold")
    fig.tight_layout()
    png_path = out_dir / "detection_rate.png"
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return csv_path, png_path


# =========================================================================== BOP19
@dataclass
class BopTarget:
    """One (image, object) target with the errors of its estimates.

    Attributes:
        inst_count: number of instances to find (BOP ``inst_count``).
        scores: (E,) estimate scores.
        visibility: (G,) GT visible fractions (all GT instances of the object in the image).
        errors: error type -> (E, G) ("mssd" normalized by the diameter, "mspd" in px at
            width 640) or (E, G, T) for "vsd" (one slice per tau).
    """

    inst_count: int
    scores: np.ndarray
    visibility: np.ndarray
    errors: dict[str, np.ndarray]


def _top_estimates(scores: np.ndarray, inst_count: int) -> np.ndarray:
    """Indices of the ``inst_count`` top-scoring estimates (descending; ties: file order)."""
    return np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")[:inst_count]


def _valid_gt(visibility: np.ndarray, inst_count: int) -> np.ndarray:
    """(G,) bool: the ``inst_count`` most visible GT instances (BOP with visib_gt_min = -1)."""
    valid = np.zeros(len(visibility), dtype=bool)
    valid[np.argsort(-np.asarray(visibility, dtype=np.float64), kind="stable")[:inst_count]] = True
    return valid


def bop_recalls(targets: list[BopTarget], error_type: str,
                thresholds: Sequence[float]) -> np.ndarray:
    """BOP19 recall per threshold (per tau x threshold for "vsd").

    Only the ``inst_count`` top-scoring estimates of each target are evaluated, only the
    ``inst_count`` most visible GT instances can be matched and are counted; matching is
    :func:`greedy_match` (strict ``error < threshold``). Recall = true positives / valid GT.

    Returns:
        (len(thresholds),), or (T, len(thresholds)) for "vsd".
    """
    n_taus = None
    tp = None
    total = 0
    for tg in targets:
        top = _top_estimates(tg.scores, tg.inst_count)
        valid = _valid_gt(tg.visibility, tg.inst_count)
        total += int(valid.sum())
        E = np.asarray(tg.errors[error_type], dtype=np.float64)
        if E.ndim == 2:
            E = E[:, :, None]
        if tp is None:
            n_taus = E.shape[2]
            tp = np.zeros((n_taus, len(thresholds)))
        if len(top) == 0 or E.shape[1] == 0:
            continue
        for k in range(n_taus):
            for j, th in enumerate(thresholds):
                m = greedy_match(E[top, :, k], tg.scores[top], th, valid)
                tp[k, j] += np.count_nonzero(m >= 0)
    if tp is None:
        shape = (len(thresholds),) if error_type != "vsd" else (len(metrics.BOP19_VSD_TAUS), len(thresholds))
        return np.zeros(shape)
    rec = tp / total if total else np.zeros_like(tp)
    return rec if error_type == "vsd" else rec[0]


def bop_mssd_error(R_e, t_e, R_g, t_g, model: ObjectModel) -> float:
    """MSSD / diameter with the BOP toolkit's short-cut: inf when ``|t_e - t_g| >= diameter``."""
    if metrics.te(t_e, t_g) >= model.diameter:
        return math.inf
    return metrics.mssd(R_e, t_e, R_g, t_g, model.points, model.symmetries) / model.diameter


def bop_mspd_error(R_e, t_e, R_g, t_g, K, width: int, model: ObjectModel) -> float:
    """MSPD in pixels scaled to an image width of 640 (no short-cut, as in the toolkit)."""
    return metrics.mspd(R_e, t_e, R_g, t_g, K, model.points, model.symmetries) * 640.0 / width


def bop_vsd_errors(R_e, t_e, R_g, t_g, depth, K, model: ObjectModel,
                   renderer: metrics.DepthRenderer | None = None) -> np.ndarray:
    """BOP19 VSD errors (one per tau); all 1 when the bounding-sphere projections are apart."""
    if not metrics.sphere_projections_overlap(0.5 * model.diameter, t_e, t_g):
        return np.ones(len(metrics.BOP19_VSD_TAUS))
    return metrics.vsd(R_e, t_e, R_g, t_g, depth, K, model.mesh, diameter=model.diameter,
                       renderer=renderer)


def bop_targets_from_gt(dataset: Dataset) -> tuple[dict[tuple[int, str], int], bool]:
    """{(frame index, class): inst_count} of GT instances with visibility >= 0.1.

    Returns:
        (targets, visibility_missing): the flag tells whether some GT had no visibility (they
        count as visible).
    """
    out: dict[tuple[int, str], int] = {}
    missing = False
    for fi, f in enumerate(dataset.frames):
        for o in f.objects:
            vis = o.visibility
            if vis is None:
                missing = True
                vis = 1.0
            if vis >= VISIB_GT_MIN:
                out[(fi, o.class_name)] = out.get((fi, o.class_name), 0) + 1
    return out, missing


def bop19_average_recall(dataset: Dataset, preds_by_frame: list[list[Prediction]],
                         models: dict[str, ObjectModel], use_vsd: bool | None = None,
                         progress: bool = False) -> dict[str, Any]:
    """BOP19 AR_VSD, AR_MSSD, AR_MSPD and AR (see the module docstring).

    Args:
        use_vsd: compute AR_VSD (None: when every frame with targets has depth and K).

    Returns:
        {"ar", "ar_vsd" (None when skipped), "ar_mssd", "ar_mspd", "recalls": {...},
        "targets", "gt_valid", "notes": [...]}.
    """
    from tqdm import tqdm

    notes = []
    if dataset.targets is not None:
        targets = {}
        for fi, f in enumerate(dataset.frames):
            for o in {o.class_name for o in f.objects}:
                oid = models[o].obj_id
                key = (f.scene_id, f.im_id, oid)
                if key in dataset.targets:
                    targets[(fi, o)] = dataset.targets[key]
        notes.append(f"targets: test_targets_bop19.json ({len(targets)} image-object targets)")
    else:
        targets, missing = bop_targets_from_gt(dataset)
        notes.append(f"targets: all GT instances with visibility >= {VISIB_GT_MIN} "
                     f"({len(targets)} image-object targets)")
        if missing:
            notes.append("some GT instances have no visibility: counted as visible")
    frames_used = sorted({fi for fi, _ in targets})
    if use_vsd is None:
        use_vsd = all(dataset.frames[fi].depth_path is not None and dataset.frames[fi].K is not None
                      for fi in frames_used)
        if not use_vsd:
            notes.append("AR_VSD skipped: not every test image has a depth image "
                         "(AR is the mean of AR_MSSD and AR_MSPD only)")
    for fi in frames_used:
        f = dataset.frames[fi]
        if f.K is None or not f.width:
            raise InputFileError(f.key, "BOP AR needs the camera intrinsics and the image width")
    procedural = sorted(n for n, m in models.items() if m.procedural)
    if procedural:
        notes.append("procedural cuboid models (no mesh) for: " + ", ".join(procedural))
    renderer = metrics.default_renderer() if use_vsd else None
    from dope_hope.io.images import read_depth_m

    per_frame: dict[int, list[tuple[str, int]]] = {}
    for (fi, cls), count in sorted(targets.items()):
        per_frame.setdefault(fi, []).append((cls, count))
    bop_targets: list[BopTarget] = []
    for fi in tqdm(frames_used, desc="BOP errors", unit="img", disable=not progress):
        f = dataset.frames[fi]
        depth = read_depth_m(f.depth_path, f.depth_scale_m) if use_vsd else None
        for cls, count in per_frame[fi]:
            model = models[cls]
            gts = [o for o in f.objects if o.class_name == cls]
            ests = [p for p in preds_by_frame[fi] if p.class_name == cls]
            scores = np.array([p.score for p in ests], dtype=np.float64)
            top = _top_estimates(scores, count)
            ests = [ests[i] for i in top]
            E, G = len(ests), len(gts)
            errs = {"mssd": np.empty((E, G)), "mspd": np.empty((E, G))}
            if use_vsd:
                errs["vsd"] = np.empty((E, G, len(metrics.BOP19_VSD_TAUS)))
            for i, p in enumerate(ests):
                for j, g in enumerate(gts):
                    errs["mssd"][i, j] = bop_mssd_error(p.R, p.t, g.R, g.t, model)
                    errs["mspd"][i, j] = bop_mspd_error(p.R, p.t, g.R, g.t, f.K, f.width, model)
                    if use_vsd:
                        errs["vsd"][i, j] = bop_vsd_errors(p.R, p.t, g.R, g.t, depth, f.K, model,
                                                           renderer)
            vis = np.array([1.0 if o.visibility is None else o.visibility for o in gts])
            bop_targets.append(BopTarget(count, scores[top], vis, errs))
    rec_mssd = bop_recalls(bop_targets, "mssd", BOP19_MSSD_THRESHOLDS)
    rec_mspd = bop_recalls(bop_targets, "mspd", BOP19_MSPD_THRESHOLDS)
    out: dict[str, Any] = {"ar_mssd": float(rec_mssd.mean()), "ar_mspd": float(rec_mspd.mean()),
                           "recalls": {"mssd": rec_mssd.tolist(), "mspd": rec_mspd.tolist()},
                           "targets": len(targets),
                           "gt_valid": int(sum(_valid_gt(t.visibility, t.inst_count).sum()
                                               for t in bop_targets))}
    if use_vsd:
        rec_vsd = bop_recalls(bop_targets, "vsd", BOP19_VSD_THRESHOLDS)
        out["ar_vsd"] = float(rec_vsd.mean())
        out["recalls"]["vsd"] = rec_vsd.tolist()
        out["ar"] = float(np.mean([out["ar_vsd"], out["ar_mssd"], out["ar_mspd"]]))
    else:
        out["ar_vsd"] = None
        out["ar"] = float(np.mean([out["ar_mssd"], out["ar_mspd"]]))
    out["notes"] = notes
    return out


# =========================================================================== orchestration
@dataclass
class EvalConfig:
    """Settings of one ``dope-hope evaluate`` run."""

    predictions: list[Path]
    dataset: Path
    fmt: str = "dope"
    metrics: list[str] = field(default_factory=lambda: [DEFAULT_METRIC])
    mesh: list[str] = field(default_factory=list)
    models_dir: Path | None = None
    mesh_units: str | None = None
    out: Path = Path("out/eval")
    methods: list[str] | None = None
    bop_ar: bool | None = None
    progress: bool = False


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "method"


def run_evaluation(cfg: EvalConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Evaluate one or more prediction files; write tables, curves and ``summary.json``.

    Returns:
        The summary dict (also written to ``<out>/summary.json``).
    """
    from dope_hope.io.predictions import read_predictions

    for m in cfg.metrics:
        if m not in METRICS:
            raise ConfigError(f"unknown metric {m!r}; use one of {', '.join(METRICS)}")
    if cfg.methods is not None and len(cfg.methods) != len(cfg.predictions):
        raise ConfigError(f"--method: {len(cfg.methods)} names for {len(cfg.predictions)} "
                          f"prediction files")
    dataset = load_dataset(cfg.dataset, cfg.fmt)
    loaded = []
    for k, path in enumerate(cfg.predictions):
        preds, meta = read_predictions(path)
        name = (cfg.methods[k] if cfg.methods else None) or meta.get("method") or Path(path).stem
        if any(p.image is None for p in preds) and dataset.fmt != "bop":
            raise InputFileError(path, "BOP CSV predictions need a BOP dataset (--format bop)")
        loaded.append((name, path, preds, assign_predictions(dataset, preds, path)))
    names = [n for n, *_ in loaded]
    if len(set(names)) != len(names):
        raise ConfigError(f"two prediction files have the same method name ({', '.join(names)}); "
                          f"name them with --method")
    classes = sorted({o.class_name for f in dataset.frames for o in f.objects} |
                     {p.class_name for _, _, preds, _ in loaded for p in preds})
    bop_ar = cfg.bop_ar if cfg.bop_ar is not None else dataset.fmt == "bop"
    models = load_models(classes, cfg.mesh, cfg.models_dir, cfg.mesh_units)
    out_dir = Path(cfg.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    primary = cfg.metrics[0]
    n_gt = sum(len(f.objects) for f in dataset.frames)
    model_notes = [f"{n}: {m.source}" for n, m in sorted(models.items())]
    summary: dict[str, Any] = {"dataset": str(dataset.root), "format": dataset.fmt,
                               "frames": len(dataset.frames), "gt_instances": n_gt,
                               "metric": primary, "metrics": list(cfg.metrics),
                               "models": {n: m.source for n, m in models.items()}, "methods": {}}
    curves = {}
    for name, path, preds, by_frame in loaded:
        log(f"{name}: {len(preds)} detections in {sum(1 for b in by_frame if b)} of "
            f"{len(dataset.frames)} images; {n_gt} GT instances")
        groups = compute_errors(dataset, by_frame, models, cfg.metrics, progress=cfg.progress)
        rows = object_table(dataset, groups, models, primary)
        for m in cfg.metrics:
            curves[(name, m)] = detection_rates(groups, models, m)
        bop = bop19_average_recall(dataset, by_frame, models, progress=cfg.progress) if bop_ar else None
        ls = [p.ls_applied for p in preds if p.ls_applied is not None]
        icp = [p.extra["icp_applied"] for p in preds if isinstance(p.extra.get("icp_applied"), bool)]
        notes = [f"dataset: {dataset.root} ({dataset.fmt} format, {len(dataset.frames)} images, "
                 f"{n_gt} GT instances)",
                 f"predictions: {path} ({len(preds)} detections"
                 + (f"; depth line search applied to {sum(ls)} of the {len(ls)} that record it"
                    if ls else "")
                 + (f"; depth ICP applied to {sum(icp)} of the {len(icp)} that record it" if icp else "")
                 + ")",
                 f"metric: {METRIC_LABELS[primary]} ({NUM_MODEL_POINTS} model points); matching "
                 f"per image and class, one-to-one, greedy in descending score, error < threshold",
                 "models: " + "; ".join(model_notes)]
        stem = _safe_name(name)
        md_path, csv_path = out_dir / f"per_object_{stem}.md", out_dir / f"per_object_{stem}.csv"
        atomic_write_text(md_path, table_markdown(rows, f"dope-hope evaluation: {name}", notes, bop))
        atomic_write_text(csv_path, table_csv(rows))
        overall = dict(summary_rows(rows)).get("overall")
        summary["methods"][name] = {
            "predictions": str(path), "detections": len(preds), "table_md": str(md_path),
            "table_csv": str(csv_path),
            "overall": None if overall is None else {
                **{f"precision_{_th_label(t)}": overall.precision[t] for t in overall.precision},
                **{f"recall_{_th_label(t)}": overall.recall[t] for t in overall.recall},
                "median_tp_error_cm": overall.median_tp_error_cm},
            "bop19": bop}
        if overall is not None:
            log(f"{name}: overall (mean of objects) " + ", ".join(
                f"P@{_th_label(t)} {_f(overall.precision[t], 3)} R@{_th_label(t)} "
                f"{_f(overall.recall[t], 3)}" for t in overall.precision))
        if bop is not None:
            log(f"{name}: BOP19 AR {_f(bop['ar'], 3)} (VSD "
                f"{'skipped' if bop['ar_vsd'] is None else _f(bop['ar_vsd'], 3)}, MSSD "
                f"{_f(bop['ar_mssd'], 3)}, MSPD {_f(bop['ar_mspd'], 3)})")
            for n in bop["notes"]:
                log(f"  {n}")
        log(f"  table: {md_path}")
    curve_csv, curve_png = write_curves(out_dir, curves, models)
    summary["detection_rate_csv"] = str(curve_csv)
    summary["detection_rate_png"] = str(curve_png)
    procedural = sorted(n for n, m in models.items() if m.procedural)
    if procedural:
        log("note: no mesh for " + ", ".join(procedural) + ": model points sampled on the catalog "
            "cuboid (procedural stand-in); pass --mesh or --models-dir for exact errors")
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1, default=float) + "\n")
    log(f"curves: {curve_png}, {curve_csv}; summary: {out_dir / 'summary.json'}")
    return summary

