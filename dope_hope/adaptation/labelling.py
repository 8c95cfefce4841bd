"""Labels from unlabelled RGB-D frames with the depth as the teacher.

Two passes over a sequence of frames (:class:`~dope_hope.io.streams.Frame`, in recording order):

1. **Detected labels** (:meth:`DepthLabeller.label_frame`): the model runs on each frame with
   its depth (the predictor's own stages: several working sizes, -LS, ICP; the settings'
   ``infer`` section) and each pose is kept only where the depth confirms it
   (:func:`dope_hope.adaptation.evidence.pose_evidence`); rejected poses are kept too, with the
   reason, for the preview and the counts.
2. **Carried labels** (:meth:`DepthLabeller.carry`): the frames are played forward, then
   backward, through the stream tracker (:class:`~dope_hope.inference.tracking.PoseTracker`,
   fed the confirmed labels only, a track confirmed by one of them, coasting at most
   ``carry.max_frames`` frames); a coasted pose is the filter's prediction refined against that
   frame's depth by -LS and ICP (the tracker's own coasting, with the predictor's settings). In a
   frame that holds no label of its class, a coasted pose that the depth confirms becomes a
   label (``source: carried``; one instance per class and frame is carried where the model
   found another): the frames where the model missed the object are
   the ones these labels teach it to detect. Each input folder is a sequence of its own
   (:func:`sequences`): nothing is carried across, and a sequence without one confirmed
   detection (:func:`unseeded`) is labelled again at ``carry.seed_scales`` first (in
   :mod:`dope_hope.adaptation.run`). With ``carry.chain`` the passes repeat, fed the
   carried labels too, until a pass adds none: a run of missed frames longer than
   ``max_frames`` is crossed by labels that the depth confirmed one frame at a time (a pose
   the depth does not confirm ends the chain there).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import PurePosixPath

import numpy as np

from dope_hope.adaptation.evidence import LabelEvidence, pose_evidence
from dope_hope.adaptation.settings import AdaptConfig
from dope_hope.geometry import project_points, projected_bbox
from dope_hope.inference.detection import Detection
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.tracking import PoseTracker
from dope_hope.io.streams import Frame
from dope_hope.refine.depth import DepthImage


@dataclass
class PoseLabel:
    """One pose of one object in one frame, with its evidence (kept or rejected).

    class_name; R (3, 3), t (3,) metres, mesh frame; projected_2d (9, 2) cuboid keypoints, px;
    bbox_2d (4,) px or None; evidence: what the depth says; detection: the model's own
    detection (None for a carried pose)."""

    class_name: str
    R: np.ndarray
    t: np.ndarray
    projected_2d: np.ndarray
    bbox_2d: np.ndarray | None
    evidence: LabelEvidence
    detection: Detection | None = None

    def to_record(self) -> dict:
        """The label at full precision (the first pass's log, :meth:`from_record`)."""
        return {"class": self.class_name, "R": np.asarray(self.R, np.float64).tolist(),
                "t": np.asarray(self.t, np.float64).tolist(),
                "projected_2d": np.asarray(self.projected_2d, np.float64).tolist(),
                "bbox_2d": None if self.bbox_2d is None else np.asarray(self.bbox_2d, np.float64).tolist(),
                "evidence": {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                             for k, v in asdict(self.evidence).items()}}

    @classmethod
    def from_record(cls, rec: dict) -> PoseLabel:
        """A label read back from :meth:`to_record` (without its detection)."""
        nan_when_none = ("residual_m", "edge", "icp_fit", "measured")
        ev = LabelEvidence(**{k: (float("nan") if v is None and k in nan_when_none else v)
                              for k, v in rec["evidence"].items()})
        return cls(rec["class"], np.array(rec["R"]), np.array(rec["t"]), np.array(rec["projected_2d"]),
                   None if rec["bbox_2d"] is None else np.array(rec["bbox_2d"]), ev)

    def to_json(self) -> dict:
        """The label's record: class, pose (metres), projected cuboid, and its evidence."""
        return {"class": self.class_name, "R": np.asarray(self.R, np.float64).round(6).tolist(),
                "t": [round(float(v), 6) for v in self.t],
                "bbox_2d": None if self.bbox_2d is None else [round(float(v), 2) for v in self.bbox_2d],
                **self.evidence.to_json()}


@dataclass
class LabelledFrame:
    """A frame's labels: index and name in the sequence, K (3, 3), image (H, W); kept and
    rejected :class:`PoseLabel` s; detected: whether the model found (a kept detection of)
    any object in it."""

    index: int
    name: str
    K: np.ndarray
    hw: tuple[int, int]
    kept: list[PoseLabel] = field(default_factory=list)
    rejected: list[PoseLabel] = field(default_factory=list)

    def to_record(self) -> dict:
        """The frame's labels at full precision (the first pass's log)."""
        return {"index": self.index, "name": self.name, "K": np.asarray(self.K).tolist(), "hw": list(self.hw),
                "kept": [lab.to_record() for lab in self.kept], "rejected": [lab.to_record() for lab in self.rejected]}

    @classmethod
    def from_record(cls, rec: dict) -> LabelledFrame:
        """A frame's labels read back from :meth:`to_record`."""
        return cls(rec["index"], rec["name"], np.array(rec["K"]), tuple(rec["hw"]),
                   [PoseLabel.from_record(r) for r in rec["kept"]], [PoseLabel.from_record(r) for r in rec["rejected"]])

    @property
    def detected(self) -> bool:
        return any(lab.evidence.source == "detected" for lab in self.kept)


def sequences(frames: Sequence[LabelledFrame]) -> list[range]:
    """The index ranges of ``frames`` that are one sequence each: consecutive frames whose
    names share a folder (the frames of one input folder; a recording's or a video's frames
    are one). The tracker never carries a pose from one sequence into another."""
    runs: list[range] = []
    start = 0
    for i in range(1, len(frames) + 1):
        if i == len(frames) or PurePosixPath(frames[i].name).parent != PurePosixPath(frames[start].name).parent:
            runs.append(range(start, i))
            start = i
    return runs


def unseeded(frames: Sequence[LabelledFrame]) -> list[int]:
    """The indices (into ``frames``) of the frames of every sequence (:func:`sequences`) in
    which no detection was confirmed: nothing can be carried there."""
    return [i for run in sequences(frames) if not any(frames[j].detected for j in run) for i in run]


def frame_depth(frame: Frame) -> DepthImage:
    """The frame's depth as a :class:`DepthImage` (metres; unusable when the frame has none)."""
    return DepthImage.from_raw(frame.depth, frame.K, 0.001, 1.0, frame.rgb.shape[:2])


class DepthLabeller:
    """Labels of one predictor's objects (module docstring).

    Args:
        predictor: the model with its inference options (``infer`` of the settings).
        settings: the whole :class:`~dope_hope.adaptation.settings.AdaptConfig` (``labels``, ``carry``).
    """

    def __init__(self, predictor: DopePredictor, settings: AdaptConfig):
        self.predictor = predictor
        self.settings = settings

    def _label(self, class_name: str, R: np.ndarray, t: np.ndarray, depth: DepthImage, score: float,
               source: str, detection: Detection | None = None, icp_fit: float = float("nan")) -> PoseLabel:
        obj = self.predictor.object_of(detection) if detection is not None else next(
            o for o in self.predictor.objects if o.class_name == class_name)
        ev = pose_evidence(R, t, obj.model_points, depth, score, self.settings.labels, source, icp_fit)
        return PoseLabel(class_name, np.asarray(R, np.float64), np.asarray(t, np.float64),
                         project_points(obj.cuboid_mesh, depth.K, R, t),
                         projected_bbox(obj.bbox_points, depth.K, R, t, depth.hw), ev, detection)

    def label_frame(self, frame: Frame) -> LabelledFrame:
        """Pass 1 on one frame: the model's detections with depth, each kept or rejected by
        its evidence. ConfigError-free: a frame without usable depth gets no label."""
        depth = frame_depth(frame)
        out = LabelledFrame(frame.index, frame.name, np.asarray(frame.K, np.float64), tuple(frame.rgb.shape[:2]))
        if not depth.usable:
            return out
        for det in self.predictor.predict(frame.rgb, frame.K, depth):
            lab = self._label(det.class_name, det.R, det.t, depth, det.score, "detected", det, det.icp_fit)
            (out.kept if lab.evidence.kept else out.rejected).append(lab)
        return out

    def carry(self, frames: Sequence[LabelledFrame], depth_of: Callable[[int], DepthImage]) -> int:
        """Pass 2: labels carried forward, then backward, by the tracker into frames that hold
        no label of their class (module docstring), added in place; ``depth_of(i)`` gives the
        depth of ``frames[i]``. Returns the number of carried labels kept."""
        c = self.settings.carry
        if not c.enabled or not frames:
            return 0
        found = 0
        for run in sequences(frames):
            added = self._carry_pass(frames, run, depth_of, ("detected",))
            found += added
            while c.chain and added:
                added = self._carry_pass(frames, run, depth_of, ("detected", "carried"))
                found += added
        return found

    def _carry_pass(self, frames: Sequence[LabelledFrame], run: range, depth_of: Callable[[int], DepthImage],
                    fed_sources: tuple[str, ...]) -> int:
        """One forward and one backward play of the tracker over ``frames[run]`` (one
        sequence), fed the kept labels of ``fed_sources``; a frame's rejected carried pose is
        recorded once (the first pass's)."""
        c = self.settings.carry
        tracking = replace(self.predictor.options.tracking, confirm_hits=1, max_coast=c.max_frames,
                           max_misses=c.max_frames)
        found = 0
        for order in (run, run[::-1]):
            tracker = PoseTracker(self.predictor, settings=tracking)
            for step, i in enumerate(order):
                f = frames[i]
                fed = [lab.detection or self._as_detection(lab) for lab in f.kept
                       if lab.evidence.source in fed_sources]
                depth = depth_of(i)
                coasted = [o for o in tracker.update(fed, f.K, depth if depth.usable else None, frame=step,
                                                     image_hw=f.hw) if o.tracked == "coasted"]
                for o in coasted:
                    if not depth.usable or any(lab.class_name == o.class_name for lab in f.kept):
                        continue  # the frame holds a label of the object: not a frame the model missed
                    lab = self._label(o.class_name, o.R, o.t, depth, o.score, "carried")
                    if lab.evidence.kept:
                        f.kept.append(lab)
                        found += 1
                    elif not any(r.class_name == o.class_name and r.evidence.source == "carried"
                                 for r in f.rejected):
                        f.rejected.append(lab)
        return found

    def _as_detection(self, lab: PoseLabel) -> Detection:
        """A label as a detection the tracker takes (a label read back has no detection)."""
        obj = next(o for o in self.predictor.objects if o.class_name == lab.class_name)
        n = len(lab.projected_2d)
        return Detection(lab.class_name, lab.evidence.score, lab.R, lab.t, lab.projected_2d.copy(), np.ones(n),
                         np.ones(n, bool), lab.projected_2d.copy(), 0.0, obj.cuboid_size_m,
                         obj.cuboid_center_m, lab.bbox_2d)
