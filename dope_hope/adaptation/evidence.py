"""Whether the depth confirms a pose: the evidence a label records and the rule that keeps it.

A pose (R, t) of an object is compared with the measured depth in three ways, each a number
of the label's evidence (:class:`LabelEvidence`):

* **measured**: the share of the object's visible surface at the pose (its surface points,
  front-most per pixel: :func:`dope_hope.refine.line_search.visible_points`), leaving out the
  points an occluder in front hides, where the sensor measured a depth at all (a stereo camera
  drops dark surfaces, depth edges and far, small objects: a missing depth says nothing for or
  against the pose, but a pose over nothing but holes has no evidence);
* **support**: the share of those measured points whose depth the sensor confirms within
  ``tolerance_m`` (a point whose depth lies behind the surface, the sensor seeing through
  where the object would be, counts against the pose);
* **residual_m**: the median |measured depth - surface depth| over those points where the
  sensor measured something (a pose 3 cm too far has a residual near 3 cm);
* **edge**: the share of the pose's silhouette outline (the convex hull of its projected
  surface, :func:`dope_hope.refine.icp.silhouette_mask`) that lies within ``edge_px`` of a
  depth edge (:func:`dope_hope.synth.depth_noise.depth_edges`: a relative jump of
  ``edge_jump``, or measured against missing depth): a pose slid sideways keeps much of its
  depth support on a flat face but its outline leaves the object's depth edges;

plus the detection's score. :func:`rejection` is the one rule that turns them into kept or
rejected (with the reason), by :class:`~dope_hope.adaptation.settings.LabelSettings`.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from dope_hope.adaptation.settings import LabelSettings
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import silhouette_mask
from dope_hope.refine.line_search import auto_splat_px, visible_points
from dope_hope.synth.depth_noise import depth_edges

#: Values of ``LabelEvidence.source``: the model's own detection, or a pose the tracker carried.
LABEL_SOURCES = ("detected", "carried")


@dataclass
class LabelEvidence:
    """What the depth says of one pose (module docstring). score: the detection's (a carried
    pose: its track's last). support, edge, measured: shares in [0, 1]. residual_m: metres
    (NaN: no measured point). points: visible, unoccluded surface points. source: one of
    :data:`LABEL_SOURCES`. icp_fit: the ICP fit of the pose (NaN: ICP did not run). kept and
    reason: the verdict of :func:`rejection` ("ok" when kept). measured: NaN in a label
    written before it was recorded."""

    score: float
    support: float
    residual_m: float
    edge: float
    points: int
    source: str = "detected"
    icp_fit: float = float("nan")
    kept: bool = False
    reason: str = ""
    measured: float = float("nan")

    def to_json(self) -> dict:
        """Plain numbers for a label's JSON (NaN as null)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else
                    round(v, 5) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def _edge_share(points_c: np.ndarray, depth: DepthImage, settings: LabelSettings) -> float:
    """The share of the outline of projected camera-frame points (N, 3) that lies within
    ``edge_px`` of a depth edge; NaN when the outline misses the image."""
    mask = silhouette_mask(points_c, depth.K, depth.hw, 0.0).astype(np.uint8)
    outline = mask & ~cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool)
    if not outline.any():
        return float("nan")
    edges = depth_edges(np.nan_to_num(depth.metres, nan=0.0), settings.edge_jump).astype(np.uint8)
    if settings.edge_px > 0:
        r = settings.edge_px
        edges = cv2.dilate(edges, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return float((outline & edges.astype(bool)).sum() / outline.sum())


def pose_evidence(R: np.ndarray, t: np.ndarray, model_points: np.ndarray, depth: DepthImage,
                  score: float, settings: LabelSettings, source: str = "detected",
                  icp_fit: float = float("nan")) -> LabelEvidence:
    """The evidence of a pose (R (3, 3), t (3,) metres) of an object whose surface points are
    ``model_points`` (N, 3) metres, against ``depth``, with its verdict (:func:`rejection`)."""
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(3)
    P = np.asarray(model_points, np.float64).reshape(-1, 3)
    X = P @ R.T + t
    Xv = X[visible_points(X, depth.K, depth.hw, auto_splat_px(P, depth.K, float(t[2])))] if t[2] > 0 else X[:0]
    uvw = Xv @ depth.K.T
    u = np.rint(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.rint(uvw[:, 1] / uvw[:, 2]).astype(np.int64)
    r = depth.metres[v, u] - Xv[:, 2]  # NaN: no depth
    with np.errstate(invalid="ignore"):
        unoccluded = ~(r < -settings.tolerance_m)
    measured = r[unoccluded & np.isfinite(r)]
    n = int(unoccluded.sum())
    ev = LabelEvidence(score=float(score),
                       support=float((np.abs(measured) <= settings.tolerance_m).mean()) if len(measured) else 0.0,
                       residual_m=float(np.median(np.abs(measured))) if len(measured) else float("nan"),
                       edge=_edge_share(X, depth, settings), points=n, source=source, icp_fit=float(icp_fit),
                       measured=len(measured) / n if n else 0.0)
    reason = rejection(ev, settings)
    ev.kept, ev.reason = reason is None, reason or "ok"
    return ev


def rejection(ev: LabelEvidence, settings: LabelSettings) -> str | None:
    """Why the depth does not confirm a pose of evidence ``ev`` (None: it does): the first of
    too few points, score, measured share, support, residual and edge below (above) its
    setting (a label written before ``measured`` was recorded is not judged by it)."""
    if ev.points < settings.min_points:
        return f"{ev.points} visible surface points (< labels.min_points {settings.min_points})"
    if ev.score < settings.min_score:
        return f"score {ev.score:.2f} < labels.min_score {settings.min_score:g}"
    if ev.measured < settings.min_measured:
        return f"depth measured on {ev.measured:.2f} of the surface < labels.min_measured {settings.min_measured:g}"
    if ev.support < settings.min_support:
        return f"depth support {ev.support:.2f} < labels.min_support {settings.min_support:g}"
    if not math.isfinite(ev.residual_m) or ev.residual_m > settings.max_residual_m:
        return f"depth residual {ev.residual_m * 1000:.1f} mm > labels.max_residual_m {settings.max_residual_m:g}"
    if not math.isfinite(ev.edge) or ev.edge < settings.min_edge:
        return f"silhouette on depth edges {ev.edge:.2f} < labels.min_edge {settings.min_edge:g}"
    return None
