"""The ROS 2 node of ``dope-hope ros2``: a camera's colour images (with their camera info and,
optionally, the aligned depth) in, the objects' poses out, stamped with each image's stamp
and frame_id. :class:`DopeHopeNode` is importable for composition in a Python launch; import
this module after :func:`dope_hope.ros.ros2_runtime.prepare_ros2_process` (a command) or
with rclpy working already (a user's own process).

**Inputs** (sensor-data QoS, ``input_reliability:=reliable`` for large raw images; relative names, remappable: ``--ros-args -r image:=/my/topic``;
unremapped, a RealSense's, :data:`INPUT_DEFAULTS`): ``image`` (sensor_msgs/Image, or
CompressedImage on ``image/compressed`` with ``image_transport:=compressed``),
``camera_info`` (paired by stamp, as image_transport's camera subscriber), ``depth``
(registered to colour: 16UC1 mm or 32FC1 m; ``use_depth:=false`` ignores it). Pairing and
the latest-frame-wins rule: :mod:`dope_hope.ros.frame_pairing`.

**Outputs** (in the node's namespace, ``~/``): ``poses`` (geometry_msgs/PoseArray, every
detection, by decreasing score), ``pose_<class>`` (geometry_msgs/PoseStamped, each class's
best detection of the frame, as the official DOPE node), ``markers``
(visualization_msgs/MarkerArray: cuboids and labels), ``overlay`` (sensor_msgs/Image rgb8;
``overlay:=false`` skips it), ``processing_time_ms`` (std_msgs/Float64: the image's arrival to
its poses published), and ``detections`` (vision_msgs/Detection3DArray in Isaac ROS DOPE's
layout) where ``vision_msgs`` is importable. Poses are the mesh frame's (x_c = R x + t), metres.

Messages are built by :class:`~dope_hope.ros.pose_messages.PoseMessages` (the poses MCAP and
the Foxglove view use the same) and travel serialized: rclpy only moves the bytes. Inference
runs in a worker thread, so the executor keeps taking messages and parameter changes while
a frame is processed; a bad image or camera info is logged and skipped.
"""
from __future__ import annotations

import importlib
import statistics
import struct
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.errors import ConfigError, DopeHopeError
from dope_hope.inference.model_choice import ModelChoice, build_run_predictors
from dope_hope.inference.model_set import stream_tracker
from dope_hope.inference.predictor import as_depth_image, predict_many
from dope_hope.io.models_dir import named_object_values
from dope_hope.ros.frame_pairing import CameraFrame, LatestFramePairing
from dope_hope.ros.node_params import (
    RUNTIME_PARAMETERS,
    NodeSettings,
    checked_classes,
    checked_min_score,
    given_inference_settings,
    inference_parameter_names,
    node_parameter_names,
)
from dope_hope.ros.outputs import posed_objects
from dope_hope.ros.pose_messages import PoseMessages
from dope_hope.ros.recordings import camera_from_info, decode_depth, decode_image
from dope_hope.viz import overlay_detections

#: Input topic -> its name when not remapped (a RealSense's, relative to the namespace).
INPUT_DEFAULTS = {"image": "camera/color/image_raw", "camera_info": "camera/color/camera_info",
                  "depth": "camera/aligned_depth_to_color/image_raw"}
#: Output topic -> message type (``pose_<class>``: geometry_msgs/msg/PoseStamped each).
OUTPUTS = {"poses": "geometry_msgs/msg/PoseArray", "markers": "visualization_msgs/msg/MarkerArray",
           "overlay": "sensor_msgs/msg/Image", "processing_time_ms": "std_msgs/msg/Float64",
           "detections": "vision_msgs/msg/Detection3DArray"}
#: Seconds between the node's progress lines in the log.
REPORT_PERIOD_S = 10.0
#: Processing times kept for the median of the progress lines.
KEPT_TIMES = 100


def message_class(msgtype: str) -> Any:
    """The rclpy class of ``pkg/msg/Name``; None where the package is not installed."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except ModuleNotFoundError:
        return None


def header_stamp_ns(raw: bytes) -> int:
    """The header stamp (ns) of a serialized message whose first field is a std_msgs/Header
    (Image, CompressedImage, CameraInfo): CDR's 4-byte encapsulation (byte 1: 1 little-endian,
    0 big-endian), then the stamp's int32 sec and uint32 nanosec; read without decoding the
    pixels."""
    sec, nanosec = struct.unpack("<iI" if raw[1] == 1 else ">iI", raw[4:12])
    return sec * 1_000_000_000 + nanosec


class DopeHopeNode(Node):
    """The pose estimation node (module docstring).

    Args:
        node_name: the node's name (default ``dope_hope``).
        base_settings: inference settings under the parameters' (``dope-hope ros2 --config /
            --set``), nested as a settings file.
        default_weights: the model when the ``weights`` parameter names none (the shipped demo model).
        **node_options: rclpy Node's keyword arguments (namespace, parameter_overrides, cli_args, ...).

    Raises:
        ConfigError: a bad parameter or model (one line naming it), before any subscription.
    """

    def __init__(self, node_name: str = "dope_hope", *, base_settings: Mapping[str, Any] | None = None,
                 default_weights: Path | None = DEMO_WEIGHTS, **node_options: Any):
        super().__init__(node_name, **node_options)
        self._declare_parameters()
        given = {n: self.get_parameter(n).value for n in node_parameter_names()}
        self.settings = NodeSettings.from_mapping({k: v if not isinstance(v, (list, tuple)) else list(v)
                                                   for k, v in given.items() if v is not None})
        settings = given_inference_settings({n: self.get_parameter(n).value for n in inference_parameter_names()
                                             if self.get_parameter(n).value is not None}, base_settings)
        s = self.settings
        choice = ModelChoice(weights=tuple(Path(w) for w in s.weights), meshes=tuple(Path(m) for m in s.mesh),
                             mesh_units=named_object_values(s.mesh_units, "mesh_units", ("m", "cm", "mm")),
                             up_axes=named_object_values(s.up_axis, "up_axis", ("x", "y", "z", "-x", "-y", "-z")),
                             start=Path(s.start) if s.start else None, classes=s.classes or None, backend=s.backend,
                             device=s.device, threads=s.threads or None)
        default = default_weights if default_weights is not None and Path(default_weights).is_file() else None
        self.predictors = build_run_predictors(choice, settings, default, note=self.get_logger().info)
        self.known_classes = [obj.class_name for p in self.predictors for obj in p.objects]
        self._own_min_scores = [[obj.min_score for obj in p.objects] for p in self.predictors]
        self.classes: tuple[str, ...] | None = checked_classes(list(s.classes) or None, self.known_classes)
        self.tracker = stream_tracker(self.predictors) if s.track else None
        self.messages = PoseMessages()
        self.pairing = LatestFramePairing(s.use_depth, s.depth_tolerance_ms / 1000.0, s.depth_wait_ms / 1000.0)
        self.skipped = 0
        self._last_error = ("", 0.0)  # the last reason logged and when
        self.processed = 0
        self.times_ms: list[float] = []
        self._cameras: dict[tuple, tuple] = {}
        self._lock = threading.Lock()  # the runtime parameters against the worker
        self._outputs: dict[str, Any] = {}
        for topic, msgtype in OUTPUTS.items():
            if topic == "overlay" and not s.overlay:
                continue
            cls = message_class(msgtype)
            if cls is not None:
                self._outputs[topic] = self.create_publisher(cls, f"~/{topic}", QoSProfile(depth=10))
        if "detections" not in self._outputs:
            self.get_logger().info("vision_msgs is not installed: no ~/detections (Detection3DArray)")
        for name in self.known_classes:
            self._pose_publisher(name)
        self.inputs = {name: self.input_topic(name) for name in INPUT_DEFAULTS}
        compressed = s.image_transport == "compressed"
        image_topic = self.inputs["image"] + ("/compressed" if compressed else "")
        self.inputs["image"] = image_topic
        self._image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        self._subscribe(self._image_type, image_topic, self.pairing.add_image)
        self._subscribe("sensor_msgs/msg/CameraInfo", self.inputs["camera_info"], self.pairing.add_info)
        if s.use_depth:
            self._subscribe("sensor_msgs/msg/Image", self.inputs["depth"], self.pairing.add_depth)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._last_report = time.perf_counter()
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work, name="dope-hope-inference", daemon=True)
        self._worker.start()
        self.get_logger().info(f"detecting {', '.join(self.known_classes)}; image {image_topic}, camera info "
                               f"{self.inputs['camera_info']}"
                               + (f", depth {self.inputs['depth']}" if s.use_depth else ", no depth"))

    # ------------------------------------------------------------------ setup
    def _declare_parameters(self) -> None:
        """Every parameter, unset unless given (its default in its description), any type."""
        defaults = {**{f: getattr(NodeSettings(), f) for f in node_parameter_names()}, **inference_parameter_names()}
        for name, default in defaults.items():
            note = " (changes at run time)" if name in RUNTIME_PARAMETERS else ""
            self.declare_parameter(name, None, ParameterDescriptor(
                dynamic_typing=True, description=f"default: {default!r}{note}"))

    def input_topic(self, name: str) -> str:
        """The input ``name`` as remapped, else its :data:`INPUT_DEFAULTS` name, resolved."""
        remapped = self.resolve_topic_name(name)
        if remapped != self.resolve_topic_name(name, only_expand=True):
            return remapped
        return self.resolve_topic_name(INPUT_DEFAULTS[name], only_expand=True)

    def _subscribe(self, msgtype: str, topic: str, add) -> None:
        qos = QoSProfile(history=qos_profile_sensor_data.history, depth=qos_profile_sensor_data.depth,
                         durability=qos_profile_sensor_data.durability,
                         reliability=(ReliabilityPolicy.RELIABLE if self.settings.input_reliability == "reliable"
                                      else qos_profile_sensor_data.reliability))
        self.create_subscription(message_class(msgtype), topic, lambda raw: add(header_stamp_ns(raw), raw), qos,
                                 raw=True)

    def _pose_publisher(self, class_name: str) -> Any:
        key = f"pose_{class_name}"
        if key not in self._outputs:
            self._outputs[key] = self.create_publisher(message_class("geometry_msgs/msg/PoseStamped"),
                                                          f"~/{key}", QoSProfile(depth=10))
        return self._outputs[key]

    # ------------------------------------------------------------------ parameters
    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """``min_score`` and ``classes`` change the next frame; a bad value or another
        parameter is refused with the reason, the node unchanged."""
        try:
            updates = {}
            for p in params:
                if p.name not in RUNTIME_PARAMETERS:
                    raise ConfigError(f"{p.name} is read at start: restart the node to change it "
                                      f"(at run time: {', '.join(RUNTIME_PARAMETERS)})")
                if p.name == "min_score":
                    updates["min_score"] = checked_min_score(p.value)
                else:
                    updates["classes"] = checked_classes(p.value, self.known_classes)
        except ConfigError as exc:
            self.get_logger().warning(f"parameter refused: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        with self._lock:
            if "min_score" in updates:
                for predictor, own in zip(self.predictors, self._own_min_scores):
                    for obj, score in zip(predictor.objects, own):
                        obj.min_score = score if updates["min_score"] is None else updates["min_score"]
            if "classes" in updates:
                self.classes = updates["classes"]
        self.get_logger().info("set " + ", ".join(f"{k}={v}" for k, v in updates.items()))
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ work
    def _work(self) -> None:
        while not self._stop.is_set():
            frame = self.pairing.take(timeout_s=0.2)
            if frame is not None:
                try:
                    self.process(frame)
                except DopeHopeError as exc:
                    self._skip(frame, f"skipped: {exc}")
                except Exception as exc:  # noqa: BLE001 - one frame's failure must not end the node
                    self._skip(frame, f"failed: {type(exc).__name__}: {exc}")
            if time.perf_counter() - self._last_report >= REPORT_PERIOD_S:
                self._last_report = time.perf_counter()
                self.get_logger().info(self.summary())

    def _skip(self, frame: CameraFrame, reason: str) -> None:
        """Count a frame that could not be processed; log its reason unless the same reason
        was logged less than a second ago (a misconfigured stream at 30 frames/s)."""
        self.skipped += 1
        now = time.perf_counter()
        if self._last_error[0] != reason or now - self._last_error[1] >= 1.0:
            self._last_error = (reason, now)
            self.get_logger().error(f"frame {frame.stamp_ns} {reason}")

    def _camera(self, info: Any) -> tuple:
        """(K, width, height, rectification) of a CameraInfo, kept per distinct calibration."""
        key = (tuple(info.k), tuple(info.d), tuple(info.r), tuple(info.p), int(info.width), int(info.height),
               info.distortion_model)
        if key not in self._cameras:
            if len(self._cameras) > 8:
                self._cameras.clear()
            self._cameras[key] = camera_from_info(info, self.inputs["camera_info"])
        return self._cameras[key]

    def decode(self, frame: CameraFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, Any]:
        """(RGB (H, W, 3) uint8, K (3, 3), depth (H, W) metres or None, the image header) of a
        paired frame, rectified where the camera is distorted; DopeHopeError naming the topic."""
        store = self.messages.store
        image = store.deserialize_cdr(frame.image, self._image_type)
        info = store.deserialize_cdr(frame.info, "sensor_msgs/msg/CameraInfo")
        K, width, height, rect = self._camera(info)
        rgb = decode_image(image, self.inputs["image"])
        if (width, height) != (None, None) and (width, height) != (rgb.shape[1], rgb.shape[0]):
            raise ConfigError(f"{self.inputs['camera_info']}: camera info for {width}x{height}, the image is "
                              f"{rgb.shape[1]}x{rgb.shape[0]}")
        depth = None
        if frame.depth is not None:
            depth = decode_depth(store.deserialize_cdr(frame.depth, "sensor_msgs/msg/Image"), self.inputs["depth"])
            if depth.shape != rgb.shape[:2]:
                raise ConfigError(f"{self.inputs['depth']}: depth is {depth.shape[1]}x{depth.shape[0]}, the image "
                                  f"{rgb.shape[1]}x{rgb.shape[0]}: not registered to colour")
        if rect is not None:
            rgb = rect.image(rgb)
            depth = None if depth is None else rect.depth(depth)
        return rgb, K, depth, image.header

    def process(self, frame: CameraFrame) -> list:
        """One paired frame: decode, detect (and track), publish; returns the published objects."""
        taken = time.perf_counter()
        rgb, K, depth, header = self.decode(frame)
        depth_image = as_depth_image(depth, K, 0.001, self.settings.depth_calibration, rgb.shape[:2])
        decoded = time.perf_counter()
        with self._lock:
            classes = self.classes
            dets = predict_many(self.predictors, rgb, K, depth=depth_image, classes=classes)
        self.get_logger().debug(f"frame {frame.stamp_ns}: waited {1000 * (taken - frame.arrival_s):.1f} ms, "
                                f"decoded {1000 * (decoded - taken):.1f} ms, detected "
                                f"{1000 * (time.perf_counter() - decoded):.1f} ms, depth {depth is not None}")
        if self.tracker is not None:
            counts = self.pairing.counts  # the frame's place in the stream, dropped frames counted
            dets = self.tracker.update(dets, K, depth_image, frame=counts.taken + counts.dropped, image_hw=rgb.shape[:2])
            if classes is not None:
                dets = [d for d in dets if d.class_name in classes]
        self.publish(frame, header, rgb, K, dets)
        return dets

    def publish(self, frame: CameraFrame, header: Any, rgb: np.ndarray, K: np.ndarray, dets: list) -> None:
        """The frame's messages, the poses first; its processing time last but the overlay."""
        m, pub = self.messages, self._outputs
        out_header = m.header(frame.stamp_ns, str(header.frame_id))
        objects = posed_objects(dets)
        pub["poses"].publish(m.serialize(m.poses(out_header, objects)))
        best: dict[str, Any] = {}
        for obj in objects:  # by decreasing score: the first of a class is its best
            best.setdefault(obj.class_name, obj)
        for name, obj in best.items():
            self._pose_publisher(name).publish(m.serialize(m.pose_stamped(out_header, obj)))
        if "detections" in pub:
            pub["detections"].publish(m.serialize(m.detections(out_header, objects)))
        pub["markers"].publish(m.serialize(m.markers(out_header, objects)))
        elapsed_ms = (time.perf_counter() - frame.arrival_s) * 1000.0
        pub["processing_time_ms"].publish(m.serialize(m.T["std_msgs/msg/Float64"](data=elapsed_ms)))
        self.processed += 1
        self.times_ms = (self.times_ms + [elapsed_ms])[-KEPT_TIMES:]
        if "overlay" in pub:
            pub["overlay"].publish(m.serialize(m.image(out_header, overlay_detections(rgb, dets, K))))

    # ------------------------------------------------------------------ end
    def summary(self) -> str:
        """Frames received, processed, dropped, skipped; the median processing time."""
        c = self.pairing.counts
        median = f"; median {statistics.median(self.times_ms):.0f} ms from arrival to poses" if self.times_ms else ""
        return (f"{c.images} image(s) received, {self.processed} processed, {c.dropped} dropped (a newer frame "
                f"came first), {c.unpaired} without camera info, {self.skipped} skipped, {c.without_depth} "
                f"without depth{median}")

    def close(self) -> None:
        """Stop the worker (the frame in progress ends first)."""
        self._stop.set()
        self.pairing.close()
        self._worker.join(timeout=30.0)
