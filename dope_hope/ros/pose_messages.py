"""A frame's poses as ROS 2 messages: what the output MCAP holds and the live Foxglove view
serves (:mod:`dope_hope.ros.recording_writer`, :mod:`dope_hope.ros.foxglove_live`), built here
once for both.

Topics (:data:`TOPICS`), every message on the image's header stamp and frame_id (the camera
frame; x right, y down, z forward, metres):

* ``/dope_hope/detections`` vision_msgs/Detection3DArray: per object one result (class_id,
  score, the object pose ``x_c = R x + t``), the bounding box (its centre's pose and the cuboid
  size, metres) and ``id`` (the track id when tracking, else empty);
* ``/dope_hope/poses`` geometry_msgs/PoseArray: the object poses, in the same order;
* ``/dope_hope/markers`` visualization_msgs/MarkerArray: a DELETEALL, then per object a CUBE
  (namespace the class, id the track id or the object's place in the frame) and a text label
  ("Class #id score");
* ``/dope_hope/annotations`` foxglove_msgs/ImageAnnotations: the projected cuboid edges
  (LINE_LIST) and the label, pixels (origin at the top-left pixel's corner, as Foxglove draws);
* ``/tf`` tf2_msgs/TFMessage: camera frame -> ``<class>_<id>`` per object;
* ``/dope_hope/overlay/compressed`` sensor_msgs/CompressedImage: the overlay image (JPEG), when
  the caller draws one.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dope_hope.geometry import (
    CUBOID_EDGES,
    cuboid_keypoints,
    matrix_to_quaternion_xyzw,
    project_points,
)
from dope_hope.ros.message_types import ros2_typestore

DETECTIONS = "/dope_hope/detections"
POSES = "/dope_hope/poses"
MARKERS = "/dope_hope/markers"
ANNOTATIONS = "/dope_hope/annotations"
TF = "/tf"
OVERLAY = "/dope_hope/overlay/compressed"
#: Topic -> ROS 2 message type of every topic written / served.
TOPICS: dict[str, str] = {
    DETECTIONS: "vision_msgs/msg/Detection3DArray",
    POSES: "geometry_msgs/msg/PoseArray",
    MARKERS: "visualization_msgs/msg/MarkerArray",
    ANNOTATIONS: "foxglove_msgs/msg/ImageAnnotations",
    TF: "tf2_msgs/msg/TFMessage",
    OVERLAY: "sensor_msgs/msg/CompressedImage",
}
#: frame_id of frames that were not recorded with one (videos, cameras).
DEFAULT_FRAME_ID = "camera"
#: Opacity of the cuboid markers.
MARKER_ALPHA = 0.5


@dataclass
class PosedObject:
    """One object of a frame as the messages need it.

    class_name; score in [0, 1]; R (3, 3), t (3,) metres (``x_c = R x + t``); size_m (3,) and
    center_m (3,) of its cuboid in the object frame, metres; track_id or None; color_rgb
    (0-255) of its drawings.
    """

    class_name: str
    score: float
    R: np.ndarray
    t: np.ndarray
    size_m: np.ndarray
    center_m: np.ndarray
    track_id: int | None = None
    color_rgb: tuple[int, int, int] = (0, 255, 0)

    def label(self) -> str:
        return f"{self.class_name}{'' if self.track_id is None else f' #{self.track_id}'} {self.score:.2f}"


def child_frame(obj: PosedObject, place: int) -> str:
    """The tf frame of an object: ``<class>_<track id>``, else ``<class>_<place>`` (1-based)."""
    return f"{obj.class_name}_{obj.track_id if obj.track_id is not None else place}"


class PoseMessages:
    """Builds the messages of :data:`TOPICS` with one typestore (:func:`ros2_typestore`)."""

    def __init__(self):
        self.store = ros2_typestore()
        self.T = self.store.types

    def serialize(self, msg: Any) -> bytes:
        """CDR bytes of a message (what the MCAP and the WebSocket carry)."""
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def definition(self, msgtype: str) -> str:
        """The ros2msg definition text of a type (with its dependencies)."""
        return self.store.generate_msgdef(msgtype, ros_version=2)[0]

    # ---------------------------------------------------------------- pieces
    def _time(self, stamp_ns: int):
        return self.T["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 1_000_000_000),
                                                     nanosec=int(stamp_ns % 1_000_000_000))

    def _header(self, stamp_ns: int, frame_id: str):
        return self.T["std_msgs/msg/Header"](stamp=self._time(stamp_ns), frame_id=frame_id)

    def _pose(self, R: np.ndarray, p: np.ndarray):
        q = matrix_to_quaternion_xyzw(np.asarray(R, dtype=np.float64))
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3])))

    def _vector(self, v: np.ndarray):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _color(self, rgb: tuple[int, int, int], alpha: float, name: str = "std_msgs/msg/ColorRGBA"):
        return self.T[name](r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=alpha)

    @staticmethod
    def _box_centre(obj: PosedObject) -> np.ndarray:
        return np.asarray(obj.R, dtype=np.float64) @ np.asarray(obj.center_m, dtype=np.float64) + np.asarray(obj.t)

    # ---------------------------------------------------------------- messages
    def detections(self, header, objects: Sequence[PosedObject]):
        T = self.T
        dets = []
        for obj in objects:
            hyp = T["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=obj.class_name, score=float(obj.score)),
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(obj.R, obj.t),
                                                               covariance=np.zeros(36, dtype=np.float64)))
            bbox = T["vision_msgs/msg/BoundingBox3D"](center=self._pose(obj.R, self._box_centre(obj)),
                                                      size=self._vector(obj.size_m))
            dets.append(T["vision_msgs/msg/Detection3D"](header=header, results=[hyp], bbox=bbox,
                                                         id="" if obj.track_id is None else str(obj.track_id)))
        return T["vision_msgs/msg/Detection3DArray"](header=header, detections=dets)

    def poses(self, header, objects: Sequence[PosedObject]):
        return self.T["geometry_msgs/msg/PoseArray"](header=header, poses=[self._pose(o.R, o.t) for o in objects])

    def markers(self, header, objects: Sequence[PosedObject]):
        T = self.T
        Marker = T["visualization_msgs/msg/Marker"]
        zero = T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)

        def marker(ns: str, mid: int, kind: int, pose, scale, color, text: str = ""):
            return Marker(header=header, ns=ns, id=mid, type=kind, action=Marker.ADD, pose=pose, scale=scale,
                          color=color, lifetime=zero, frame_locked=False, points=[], colors=[],
                          texture_resource="", texture=T["sensor_msgs/msg/CompressedImage"](
                              header=header, format="", data=np.zeros(0, dtype=np.uint8)),
                          uv_coordinates=[], text=text, mesh_resource="",
                          mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
                          mesh_use_embedded_materials=False)

        identity = self._pose(np.eye(3), np.zeros(3))
        out = [marker("", 0, Marker.CUBE, identity, self._vector(np.zeros(3)), self._color((0, 0, 0), 0.0))]
        out[0].action = Marker.DELETEALL
        for place, obj in enumerate(objects, 1):
            mid = obj.track_id if obj.track_id is not None else place
            centre = self._box_centre(obj)
            out.append(marker(obj.class_name, mid, Marker.CUBE, self._pose(obj.R, centre), self._vector(obj.size_m),
                              self._color(obj.color_rgb, MARKER_ALPHA)))
            above = centre - np.asarray(obj.R)[:, 1] * (0.5 * float(np.max(obj.size_m)) + 0.02)
            out.append(marker(f"{obj.class_name}/label", mid, Marker.TEXT_VIEW_FACING, self._pose(np.eye(3), above),
                              self._vector([0.0, 0.0, 0.03]), self._color(obj.color_rgb, 1.0), obj.label()))
        return T["visualization_msgs/msg/MarkerArray"](markers=out)

    def annotations(self, stamp_ns: int, objects: Sequence[PosedObject], K: np.ndarray):
        T = self.T
        Point2, Color = T["foxglove_msgs/msg/Point2"], "foxglove_msgs/msg/Color"
        stamp = self._time(stamp_ns)
        points, texts = [], []
        for obj in objects:
            corners = cuboid_keypoints(np.asarray(obj.size_m), np.asarray(obj.center_m))
            cam = corners @ np.asarray(obj.R).T + np.asarray(obj.t)
            if np.any(cam[:, 2] <= 0):
                continue  # behind the camera: nothing to draw
            uv = project_points(corners, K, obj.R, obj.t) + 0.5  # Foxglove: origin at the pixel's corner
            segs = [Point2(x=float(uv[k][0]), y=float(uv[k][1])) for e in CUBOID_EDGES for k in e]
            points.append(T["foxglove_msgs/msg/PointsAnnotation"](
                timestamp=stamp, type=T["foxglove_msgs/msg/PointsAnnotation"].LINE_LIST, points=segs,
                outline_color=self._color(obj.color_rgb, 1.0, Color), outline_colors=[],
                fill_color=self._color((0, 0, 0), 0.0, Color), thickness=2.0))
            u0, v0 = uv[:8].min(axis=0)
            texts.append(T["foxglove_msgs/msg/TextAnnotation"](
                timestamp=stamp, position=Point2(x=float(u0), y=float(v0)), text=obj.label(), font_size=14.0,
                text_color=self._color((255, 255, 255), 1.0, Color),
                background_color=self._color(obj.color_rgb, 0.7, Color)))
        return T["foxglove_msgs/msg/ImageAnnotations"](circles=[], points=points, texts=texts)

    def transforms(self, header, objects: Sequence[PosedObject]):
        T = self.T
        tfs = []
        for place, obj in enumerate(objects, 1):
            q = matrix_to_quaternion_xyzw(np.asarray(obj.R, dtype=np.float64))
            tfs.append(T["geometry_msgs/msg/TransformStamped"](
                header=header, child_frame_id=child_frame(obj, place),
                transform=T["geometry_msgs/msg/Transform"](
                    translation=self._vector(obj.t),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                             w=float(q[3])))))
        return T["tf2_msgs/msg/TFMessage"](transforms=tfs)

    def compressed_image(self, header, data: bytes, fmt: str = "jpeg"):
        return self.T["sensor_msgs/msg/CompressedImage"](header=header, format=fmt,
                                                         data=np.frombuffer(data, dtype=np.uint8))

    def header(self, stamp_ns: int, frame_id: str):
        """A std_msgs/Header on ``stamp_ns`` (ns) in ``frame_id``."""
        return self._header(stamp_ns, frame_id)

    def pose_stamped(self, header, obj: PosedObject):
        """geometry_msgs/PoseStamped of one object's pose (as the official DOPE node's pose_CLASS)."""
        return self.T["geometry_msgs/msg/PoseStamped"](header=header, pose=self._pose(obj.R, obj.t))

    def image(self, header, rgb: np.ndarray):
        """sensor_msgs/Image rgb8 of an (H, W, 3) uint8 RGB image."""
        rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
        h, w = rgb.shape[:2]
        return self.T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding="rgb8", is_bigendian=0,
                                               step=w * 3, data=rgb.reshape(-1))

    def frame(self, stamp_ns: int, frame_id: str, objects: Sequence[PosedObject], K: np.ndarray,
              overlay_jpeg: bytes | None = None) -> list[tuple[str, Any]]:
        """(topic, message) of one frame, every topic of :data:`TOPICS` (the overlay only when
        ``overlay_jpeg`` is given)."""
        header = self._header(stamp_ns, frame_id)
        out = [(DETECTIONS, self.detections(header, objects)), (POSES, self.poses(header, objects)),
               (MARKERS, self.markers(header, objects)), (ANNOTATIONS, self.annotations(stamp_ns, objects, K)),
               (TF, self.transforms(header, objects))]
        if overlay_jpeg is not None:
            out.append((OVERLAY, self.compressed_image(header, overlay_jpeg)))
        return out
