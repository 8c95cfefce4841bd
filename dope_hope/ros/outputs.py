"""A stream's poses as ROS 2 messages: the output MCAP and the live Foxglove view of ``infer``.

:class:`RosOutputs` is the stream loop's ``on_frame`` sink (:class:`~dope_hope.inference.stream_inference.StreamSinks`):
each frame's detections (or tracked objects) become the messages of
:mod:`dope_hope.ros.pose_messages`, stamped with the frame's recorded stamp and frame_id (a
video or camera frame: the wall-clock time of the stream's first frame plus its timestamp, and
``camera``; a stamp before 1970, which neither an MCAP nor Foxglove can log, is refused), and go to a
:class:`~dope_hope.ros.recording_writer.RecordingWriter` and/or a
:class:`~dope_hope.ros.foxglove_live.FoxgloveLive` server: one set of messages for both.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.io.streams import Frame, FrameSource, is_recording
from dope_hope.ros.foxglove_live import FoxgloveLive
from dope_hope.ros.pose_messages import DEFAULT_FRAME_ID, PosedObject, PoseMessages
from dope_hope.ros.recording_writer import RecordingWriter
from dope_hope.viz import class_color, overlay_detections

#: JPEG quality of the overlay images.
JPEG_QUALITY = 90


def posed_objects(dets: Sequence[Any]) -> list[PosedObject]:
    """:class:`PosedObject` of each Detection / TrackedObject (the published pose, its box,
    the track id when tracking, the overlay's class colour)."""
    return [PosedObject(class_name=d.class_name, score=float(d.score), R=np.asarray(d.R), t=np.asarray(d.t),
                        size_m=np.asarray(d.cuboid_size_m), center_m=np.asarray(d.cuboid_center_m),
                        track_id=getattr(d, "track_id", None), color_rgb=tuple(int(c) for c in class_color(d.class_name)))
            for d in dets]


def frame_stamp(frame: Frame, start_ns: int = 0) -> tuple[int, str]:
    """(stamp ns, frame_id) of a frame: the recorded header's, else ``start_ns`` plus its
    timestamp and ``camera``."""
    stamp = frame.stamp_ns if frame.stamp_ns is not None else start_ns + round(frame.timestamp_s * 1e9)
    if stamp < 0:  # MCAP and Foxglove log times are unsigned nanoseconds since 1970
        raise InputFileError(frame.name, f"header stamp {stamp / 1e9:.9f} s is before 1970 (a valid ROS 2 time, "
                                         "but the poses MCAP and Foxglove log times start at 1970)")
    return stamp, frame.frame_id or DEFAULT_FRAME_ID


class RosOutputs:
    """``on_frame`` sink writing each frame's messages to ``writer`` and/or ``live``.

    Args:
        writer: a RecordingWriter, or None. live: a FoxgloveLive server, or None.
        overlays: also send the overlay image (JPEG CompressedImage).
    """

    def __init__(self, writer: Any = None, live: Any = None, overlays: bool = True):
        self.writer, self.live, self.overlays = writer, live, overlays
        self.messages = live.messages if live is not None else PoseMessages()
        self.frames = 0
        self.start_ns: int | None = None  # wall clock at the first frame (frames recorded without a stamp)

    def on_frame(self, frame: Frame, dets: Sequence[Any]) -> None:
        if self.start_ns is None:
            self.start_ns = time.time_ns() - round(frame.timestamp_s * 1e9)
        stamp, frame_id = frame_stamp(frame, self.start_ns)
        jpeg = None
        if self.overlays:
            bgr = cv2.cvtColor(overlay_detections(frame.rgb, dets, frame.K), cv2.COLOR_RGB2BGR)
            jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1].tobytes()
        for topic, msg in self.messages.frame(stamp, frame_id, posed_objects(dets), frame.K, jpeg):
            if self.writer is not None:
                self.writer.write(topic, stamp, msg)
            if self.live is not None:
                self.live.publish(topic, stamp, msg)
        self.frames += 1

    def close(self) -> Any:
        """Finish: the MCAP moved into place (its folder, or None) and the server stopped."""
        try:
            return None if self.writer is None else self.writer.close()
        finally:
            if self.live is not None:
                self.live.close()

    def discard(self) -> None:
        """Drop the MCAP and stop the server."""
        if self.writer is not None:
            self.writer.discard()
        if self.live is not None:
            self.live.close()


def open_ros_outputs(out: Path, source: FrameSource, foxglove_port: int | None, overlays: bool = True,
                     tell: Callable[[str], None] | None = None) -> RosOutputs | None:
    """``infer``'s ROS outputs of a stream: the poses MCAP ``out/<name>_poses`` for a recording
    (:func:`~dope_hope.io.streams.is_recording`), the Foxglove server when ``foxglove_port`` is
    given (``tell`` says where to connect; a file source then waits for the app to subscribe);
    None when neither."""
    recorded = is_recording(str(getattr(source, "path", "")))
    if not recorded and foxglove_port is None:
        return None
    outputs = RosOutputs(None, None, overlays)
    try:
        if foxglove_port is not None:
            outputs.live = FoxgloveLive(foxglove_port)
            outputs.messages = outputs.live.messages
        if recorded:
            outputs.writer = RecordingWriter(out / f"{Path(source.name).stem}_poses")
        if outputs.live is not None:
            if tell is not None:
                tell(f"Foxglove: open connection {outputs.live.url}"
                     + ("" if source.live else " (playback starts when the app subscribes)"))
            if not source.live:
                outputs.live.wait_for_client()
    except BaseException:
        outputs.discard()
        raise
    return outputs
