"""HOPE-paper reports: per-object tables (Markdown, CSV) and recall curves (JSON, PNG).

Per object: diameter, mean GT visibility, pixels (mean area of the GT 2D silhouette: convex
hull of the projected model points, occlusion ignored, px^2), distance (mean GT camera distance
of the model origin), the median error of the true positives at 10 cm, precision (TP /
detections) and recall (TP / GT instances) at 2 cm and 10 cm; category and overall rows are
means over the objects that have GT instances. Detection rate (recall) vs threshold 0.5 .. 10
cm is pooled over the GT instances of a group (all, a category, an object).
"""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from dope_hope.annotation import ObjectAnnotation
from dope_hope.evaluation.datasets import Dataset
from dope_hope.evaluation.matching import (
    CURVE_THRESHOLDS_M,
    METRIC_LABELS,
    TABLE_THRESHOLDS_M,
    UNCOUNTED,
    GroupErrors,
    counted_matches,
)
from dope_hope.evaluation.object_models import ObjectModel

CATEGORY_ORDER = ("cylinder", "cuboid", "bottle")


# =========================================================================== HOPE tables
def _projected_area_px(gt: ObjectAnnotation, model: ObjectModel, K: np.ndarray | None) -> float:
    """Area (px^2) of the convex hull of the projected model points; NaN if unknown."""
    if K is None:
        return math.nan

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


def _matched_errors(groups: list[GroupErrors], metric: str,
                    threshold: float) -> tuple[dict[str, list[float]], dict[str, int]]:
    """(class -> errors of the true positives at ``threshold``, class -> estimates matched to
    an instance under the visible floor: no detection of the table)."""
    out: dict[str, list[float]] = {}
    uncounted: dict[str, int] = {}
    for g in groups:
        E = g.errors[metric]
        m = counted_matches(g, metric, threshold)
        out.setdefault(g.class_name, []).extend(float(E[i, j]) for i, j in enumerate(m) if j >= 0)
        uncounted[g.class_name] = uncounted.get(g.class_name, 0) + int(np.count_nonzero(m == UNCOUNTED))
    return out, uncounted


def object_table(dataset: Dataset, groups: list[GroupErrors], models: dict[str, ObjectModel],
                 metric: str, thresholds: Sequence[float] = TABLE_THRESHOLDS_M) -> list[ObjectRow]:
    """Per-object rows (objects with GT or predictions), ordered by category then name."""
    n_gt: dict[str, int] = {}
    n_pred: dict[str, int] = {}
    stats: dict[str, dict[str, list[float]]] = {}
    for g in groups:
        n_gt[g.class_name] = n_gt.get(g.class_name, 0) + g.n_counted
        n_pred[g.class_name] = n_pred.get(g.class_name, 0) + len(g.scores)
        s = stats.setdefault(g.class_name, {"vis": [], "pix": [], "dist": []})
        K = dataset.frames[g.frame].K
        for k, o in enumerate(g.gt):
            if g.counted is not None and not g.counted[k]:
                continue
            s["vis"].append(math.nan if o.visibility is None else float(o.visibility))
            s["pix"].append(_projected_area_px(o, models[g.class_name], K))
            s["dist"].append(float(np.linalg.norm(o.t)))
    matched = {th: _matched_errors(groups, metric, th) for th in thresholds}
    tps = {th: m[0] for th, m in matched.items()}
    med_th = max(thresholds)
    rows = []
    for name in n_gt:
        model = models[name]
        prec, rec, tp = {}, {}, {}
        for th in thresholds:
            k = len(tps[th].get(name, []))
            tp[th] = k
            detections = n_pred[name] - matched[th][1].get(name, 0)
            prec[th] = k / detections if detections else math.nan
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
    (pooled over the group's instances; those under the visible floor count in neither).
    """
    out: dict[str, dict[str, Any]] = {}

    def bucket(name: str) -> dict[str, Any]:
        return out.setdefault(name, {"gt": 0, "tp": [0] * len(thresholds)})

    for g in groups:
        cat = models[g.class_name].category
        for name in ("overall", cat, g.class_name):
            bucket(name)["gt"] += g.n_counted
        for k, th in enumerate(thresholds):
            n = int(np.count_nonzero(counted_matches(g, metric, th) >= 0))
            for name in ("overall", cat, g.class_name):
                bucket(name)["tp"][k] += n
    for b in out.values():
        b["rate"] = [t / b["gt"] if b["gt"] else math.nan for t in b["tp"]]
    return out


def render_curves(curves: dict[tuple[str, str], dict[str, dict[str, Any]]],
                  models: dict[str, ObjectModel],
                  thresholds: Sequence[float] = CURVE_THRESHOLDS_M) -> tuple[bytes, bytes]:
    """The bytes of ``detection_rate.csv`` (every group) and ``detection_rate.png`` (overall +
    categories).

    Args:
        curves: {(method, metric): detection_rates(...)}.
    """
    import matplotlib  # noqa: PLC0415 (matplotlib (slow to import) only for the curves)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 (after matplotlib.use chose the Agg backend)

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
    csv_bytes = buf.getvalue().encode("utf-8")

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
    if axes[0][0].get_legend_handles_labels()[0]:  # no curve without ground truth
        axes[0][0].legend(loc="lower right", fontsize="small")
    if len(metrics_used) == 1:
        fig.suptitle(f"detection rate vs {METRIC_LABELS[next(iter(metrics_used))]} threshold")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110)
    plt.close(fig)
    return csv_bytes, png.getvalue()
