"""Poses on a stream: each frame of a video file, camera or RealSense through the predictors
(and a tracker), its detection records handed on, its overlay drawn: the loop of `dope-hope
infer` on a stream, which the benchmarks play too (bench/stream.py, bench/tracking.py).

The frame loop itself (dropping what it cannot keep up with, pacing, Ctrl-C) is
:func:`dope_hope.inference.frame_loop.run_stream`.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from dope_hope.inference.frame_loop import StreamStats, run_stream
from dope_hope.io.streams import Frame, FrameSource
from dope_hope.viz import overlay_detections


@dataclass
class StreamSinks:
    """Where a stream's results go (each optional).

    on_record: called with each detection record (the dict of ``Detection.to_json`` with
    ``time`` (s, this frame's processing), ``frame`` and ``timestamp_s``; a recorded frame's
    ``stamp_ns`` and ``frame_id``), in order.
    on_frame: called with each processed frame and its detections.
    video: an :class:`~dope_hope.io.video.OverlayVideo` (``write`` / ``repeat_last``): a
    dropped frame repeats the last overlay, so the video keeps the source's timing.
    window: a :class:`~dope_hope.io.video.LiveWindow` (``show`` returns False to stop).
    """

    on_record: Callable[[dict], None] | None = None
    on_frame: Callable[[Frame, list], None] | None = None
    video: Any = None
    window: Any = None


@dataclass
class StreamResult:
    """stats: what the loop did (:class:`StreamStats`); records: every detection record."""

    stats: StreamStats
    records: list[dict] = field(default_factory=list)


def predict_stream(source: FrameSource, predictors: Sequence[Any], sinks: StreamSinks | None = None,
                   tracker: Any = None, depth_calibration: float = 1.0, pace: bool = False,
                   max_frames: int | None = None, progress: bool = False,
                   warn: Callable[[str], None] | None = None) -> StreamResult:
    """Run ``predictors`` (:class:`~dope_hope.inference.predictor.DopePredictor`, one forward
    pass each per frame) on every frame ``source`` delivers, the frame's depth (integer mm or
    float metres, times ``depth_calibration``) feeding -LS / ICP.

    Args:
        tracker: a :class:`~dope_hope.inference.tracking.PoseTracker`, or None (per-frame poses).
        pace / max_frames: as :func:`~dope_hope.inference.frame_loop.run_stream`.
        progress: a progress bar on stderr (files of two or more frames).
        warn: told when a live source fails after delivering frames (the stream then ends
            with what it has) and when a file ends before the frames it states.

    Returns:
        The loop's stats and every record.
    """
    from dope_hope.inference.predictor import as_depth_image, predict_many  # noqa: PLC0415 (torch comes with the predictors: after frame_loop.passive_openmp())

    sinks = sinks or StreamSinks()
    records: list[dict] = []
    last_index: int | None = None
    bar = tqdm(total=source.length, desc="infer", unit="frame",
               disable=not progress or source.live or (source.length or 0) < 2)

    def process(frame: Frame) -> bool:
        nonlocal last_index
        t0 = time.perf_counter()
        depth = as_depth_image(frame.depth, frame.K, 0.001, depth_calibration, frame.rgb.shape[:2])
        dets = predict_many(list(predictors), frame.rgb, frame.K, depth=depth)
        if tracker is not None:
            dets = tracker.update(dets, frame.K, depth, frame=frame.index, image_hw=frame.rgb.shape[:2])
        extra = {"time": round(time.perf_counter() - t0, 4), "frame": frame.index,
                 "timestamp_s": round(frame.timestamp_s, 4)}
        if frame.stamp_ns is not None:  # a recorded image: its header's stamp and frame_id
            extra.update(stamp_ns=frame.stamp_ns, frame_id=frame.frame_id)
        for d in dets:
            rec = d.to_json(frame.name, **extra)
            records.append(rec)
            if sinks.on_record is not None:
                sinks.on_record(rec)
        if sinks.on_frame is not None:
            sinks.on_frame(frame, dets)
        bar.update(frame.index + 1 - bar.n)  # the position in the source (dropped frames too)
        keep_going = True
        if sinks.video is not None or sinks.window is not None:
            overlay = overlay_detections(frame.rgb, dets, frame.K)
            if sinks.video is not None:  # dropped frames: the last overlay stands in for them
                sinks.video.repeat_last(0 if last_index is None else frame.index - last_index - 1)
                sinks.video.write(overlay)
            if sinks.window is not None:
                keep_going = sinks.window.show(overlay)
        last_index = frame.index
        return keep_going

    def source_failed(exc: BaseException) -> bool:
        """A camera that stops after delivering frames ends the stream (outputs kept)."""
        if source.live and last_index is not None:
            if warn is not None:
                warn(f"stream ended: {exc}")
            return True
        return False

    try:
        stats = run_stream(source, process, pace=pace, max_frames=max_frames, on_source_error=source_failed,
                           warn=warn)
    finally:
        bar.close()
    if stats.expected is not None and warn is not None:
        warn(f"{source.name}: the stream ended early: {stats.read} of the {stats.expected} frames the "
             "file states could be decoded (corrupt or truncated file); the outputs hold those")
    return StreamResult(stats, records)
