"""``dope-hope evaluate``: predictions + dataset -> tables, curves and BOP19 AR in a folder.

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
submission CSV (``METHOD_hope-test.csv``) is accepted too, and so is a folder of official DOPE
inference output (per-image JSON; :func:`dope_hope.io.predictions.read_official_dope_output`),
whose poses of the cuboid centre are moved to the mesh origin (:func:`cuboid_centres_to_origins`).

Errors are ADD-H by default (500 model points); ``add``, ``adds``, ``meanssd``, ``mssd`` on
request (:mod:`~dope_hope.evaluation.matching`), over the GT instances at least
``min_visible`` visible (default every annotated instance, HOPE's own convention; 0.1 BOP19's);
tables and curves in
:mod:`~dope_hope.evaluation.reports`; BOP19 AR in :mod:`~dope_hope.evaluation.bop19`.
"""
from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.evaluation.bop19 import bop19_average_recall
from dope_hope.evaluation.datasets import Dataset, assign_predictions, load_dataset
from dope_hope.evaluation.matching import (
    DEFAULT_METRIC,
    DEFAULT_MIN_VISIBLE,
    METRIC_LABELS,
    METRICS,
    VISIBLE_FLOORS,
    compute_errors,
    visible_enough,
    visible_floor,
)
from dope_hope.evaluation.object_models import NUM_MODEL_POINTS, ObjectModel, load_models
from dope_hope.evaluation.reports import (
    _f,
    _th_label,
    detection_rates,
    object_table,
    render_curves,
    summary_rows,
    table_csv,
    table_markdown,
)
from dope_hope.io.atomic import atomic_write_files
from dope_hope.io.meshes import mesh_cuboid
from dope_hope.io.predictions import read_predictions

if TYPE_CHECKING:
    from dope_hope.io.predictions import Prediction


# =========================================================================== orchestration
@dataclass
class EvalConfig:
    """Settings of one ``dope-hope evaluate`` run."""

    predictions: list[Path]
    dataset: Path
    fmt: str = "auto"
    metrics: list[str] = field(default_factory=lambda: [DEFAULT_METRIC])
    mesh: list[str] = field(default_factory=list)
    models_dir: Path | None = None
    mesh_units: str | None = None
    out: Path = Path("out/eval")
    methods: list[str] | None = None
    bop_ar: bool | None = None
    progress: bool = False
    symmetries: list[str] = field(default_factory=list)
    official_frame: str = "legacy"
    min_visible: float | str = DEFAULT_MIN_VISIBLE  # a fraction, or a name of VISIBLE_FLOORS


def floor_label(min_visible: float) -> str:
    """The visible floor as the reports name it: its convention's name where it is one."""
    names = [k for k, v in VISIBLE_FLOORS.items() if v == min_visible]
    return f"{min_visible:g}" + (f" ({names[0]})" if names else "")


def cuboid_centres_to_origins(preds: list[Prediction], models: dict[str, ObjectModel]) -> None:
    """Give predictions that place the bounding box's centre (``origin == "cuboid"``: official
    DOPE output) the mesh origin's translation, in place: ``t - R c`` with c the centre of
    the model's box in the mesh frame (0 for the centred HOPE meshes)."""
    centres: dict[str, np.ndarray] = {}
    for p in preds:
        if p.origin != "cuboid":
            continue
        if p.class_name not in centres:
            mesh = models[p.class_name].mesh
            centres[p.class_name] = np.zeros(3) if mesh is None else mesh_cuboid(mesh)[1]
        p.t = p.t - p.R @ centres[p.class_name]
        p.origin = "mesh"


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "method"


def _load_predictions(cfg: EvalConfig, dataset: Dataset, log: Callable[[str], None]) -> list[tuple]:
    """[(method name, path, predictions, predictions per dataset frame)] of every file; names
    from ``--method``, else the file's header, else its stem (each once)."""
    loaded = []
    for k, path in enumerate(cfg.predictions):
        preds, meta = read_predictions(path, cfg.official_frame)
        name = (cfg.methods[k] if cfg.methods else None) or meta.get("method") or Path(path).stem
        if any(p.image is None for p in preds) and dataset.fmt != "bop":
            raise InputFileError(path, "BOP CSV predictions need a BOP dataset (--format bop)")
        by_frame, ignored = assign_predictions(dataset, preds, path)
        if ignored:
            log(f"{name}: {ignored} estimates of images that are not in {dataset.root} ignored "
                f"(as the BOP toolkit ignores estimates that are not targets)")
        loaded.append((name, path, preds, by_frame))
    names = [n for n, *_ in loaded]
    if len(set(names)) != len(names):
        raise ConfigError(f"two prediction files have the same method name ({', '.join(names)}); "
                          f"name them with --method")
    return loaded


def counted_instances(dataset: Dataset, min_visible: float) -> int:
    """The dataset's GT instances at least ``min_visible`` visible (a missing visibility counts as 1)."""
    return sum(int(np.count_nonzero(visible_enough(f.objects, min_visible))) for f in dataset.frames)


def _report_notes(dataset: Dataset, path: Path, preds: list[Prediction], primary: str,
                  models: dict[str, ObjectModel], min_visible: float) -> list[str]:
    """The lines above a method's table: dataset, predictions (how many were refined), metric,
    the instances counted, models."""
    n_gt = sum(len(f.objects) for f in dataset.frames)
    ls = [p.ls_applied for p in preds if p.ls_applied is not None]
    icp = [p.extra["icp_applied"] for p in preds if isinstance(p.extra.get("icp_applied"), bool)]
    return [f"dataset: {dataset.root} ({dataset.fmt} format, {len(dataset.frames)} images, "
            f"{n_gt} GT instances)",
            f"predictions: {path} ({len(preds)} detections"
            + (f"; depth line search applied to {sum(ls)} of the {len(ls)} that record it"
               if ls else "")
            + (f"; depth ICP applied to {sum(icp)} of the {len(icp)} that record it" if icp else "")
            + ")",
            f"metric: {METRIC_LABELS[primary]} ({NUM_MODEL_POINTS} model points); matching "
            f"per image and class, one-to-one, greedy in descending score, error < threshold",
            f"GT instances counted: {counted_instances(dataset, min_visible)} of {n_gt}, those at least "
            f"{floor_label(min_visible)} visible (a detection of one under it is not counted)",
            "models: " + "; ".join(f"{n}: {m.source}" for n, m in sorted(models.items()))]


def _log_results(name: str, overall: Any, bop: dict[str, Any] | None, md_path: Path,
                 log: Callable[[str], None]) -> None:
    """A method's overall precision / recall, BOP19 AR and table path, one line each."""
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


def _evaluate_method(cfg: EvalConfig, dataset: Dataset, models: dict[str, ObjectModel], method: tuple,
                     bop_ar: bool, files: dict[Path, bytes], curves: dict,
                     log: Callable[[str], None]) -> dict[str, Any]:
    """One predictions file: its tables into ``files``, its curves into ``curves``; returns its
    summary entry."""
    name, path, preds, by_frame = method
    primary = cfg.metrics[0]
    log(f"{name}: {len(preds)} detections in {sum(1 for b in by_frame if b)} of "
        f"{len(dataset.frames)} images; {sum(len(f.objects) for f in dataset.frames)} GT instances")
    groups = compute_errors(dataset, by_frame, models, cfg.metrics, progress=cfg.progress,
                            min_visible=cfg.min_visible)
    rows = object_table(dataset, groups, models, primary)
    for m in cfg.metrics:
        curves[(name, m)] = detection_rates(groups, models, m)
    bop = bop19_average_recall(dataset, by_frame, models, progress=cfg.progress) if bop_ar else None
    notes = _report_notes(dataset, path, preds, primary, models, cfg.min_visible)
    stem = _safe_name(name)
    out_dir = Path(cfg.out)
    md_path, csv_path = out_dir / f"per_object_{stem}.md", out_dir / f"per_object_{stem}.csv"
    files[md_path] = table_markdown(rows, f"dope-hope evaluation: {name}", notes, bop).encode("utf-8")
    files[csv_path] = table_csv(rows).encode("utf-8")
    overall = dict(summary_rows(rows)).get("overall")
    _log_results(name, overall, bop, md_path, log)
    return {"predictions": str(path), "detections": len(preds), "table_md": str(md_path),
            "table_csv": str(csv_path),
            "overall": None if overall is None else {
                **{f"precision_{_th_label(t)}": overall.precision[t] for t in overall.precision},
                **{f"recall_{_th_label(t)}": overall.recall[t] for t in overall.recall},
                "median_tp_error_cm": overall.median_tp_error_cm},
            "bop19": bop}


def run_evaluation(cfg: EvalConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Evaluate one or more prediction files; write tables, curves and ``summary.json``.

    Returns:
        The summary dict (also written to ``<out>/summary.json``).
    """
    for m in cfg.metrics:
        if m not in METRICS:
            raise ConfigError(f"unknown metric {m!r}; use one of {', '.join(METRICS)}")
    cfg = replace(cfg, min_visible=visible_floor(cfg.min_visible))
    if cfg.methods is not None and len(cfg.methods) != len(cfg.predictions):
        raise ConfigError(f"--method: {len(cfg.methods)} names for {len(cfg.predictions)} "
                          f"prediction files")
    dataset = load_dataset(cfg.dataset, cfg.fmt)
    loaded = _load_predictions(cfg, dataset, log)
    gt_classes = {o.class_name for f in dataset.frames for o in f.objects}
    classes = sorted(gt_classes | {p.class_name for _, _, preds, _ in loaded for p in preds})
    bop_ar = cfg.bop_ar if cfg.bop_ar is not None else dataset.fmt == "bop"
    models = load_models(classes, cfg.mesh, cfg.models_dir, cfg.mesh_units, symmetry_args=cfg.symmetries,
                         recorded_sizes=dataset.cuboid_sizes, mesh_required=gt_classes)
    for name, model in models.items():
        if model.found_symmetries:
            log(f"symmetries: {name}: {model.found_symmetries}")
    for _, _, preds, _ in loaded:
        cuboid_centres_to_origins(preds, models)
    out_dir = Path(cfg.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"dataset": str(dataset.root), "format": dataset.fmt,
                               "frames": len(dataset.frames),
                               "gt_instances": sum(len(f.objects) for f in dataset.frames),
                               "min_visible": cfg.min_visible,
                               "gt_instances_counted": counted_instances(dataset, cfg.min_visible),
                               "metric": cfg.metrics[0], "metrics": list(cfg.metrics),
                               "models": {n: m.source for n, m in models.items()}, "methods": {}}
    curves: dict = {}
    files: dict[Path, bytes] = {}  # written all or none at the end
    for method in loaded:
        summary["methods"][method[0]] = _evaluate_method(cfg, dataset, models, method, bop_ar, files,
                                                         curves, log)
    curve_csv, curve_png = out_dir / "detection_rate.csv", out_dir / "detection_rate.png"
    files[curve_csv], files[curve_png] = render_curves(curves, models)
    summary["detection_rate_csv"] = str(curve_csv)
    summary["detection_rate_png"] = str(curve_png)
    procedural = sorted(n for n, m in models.items() if m.procedural)
    if procedural:
        log("note: no mesh for " + ", ".join(procedural) + ": model points sampled on the catalog "
            "cuboid (procedural stand-in); pass --mesh or --models-dir for exact errors")
    files[out_dir / "summary.json"] = (json.dumps(summary, indent=1, default=float) + "\n").encode("utf-8")
    atomic_write_files(files)  # all or nothing: a full disk leaves no half set of tables
    log(f"curves: {curve_png}, {curve_csv}; summary: {out_dir / 'summary.json'}")
    return summary
