"""Robot recordings written for the tests by rosbags' own writers, with the real message types.

:func:`write_recording` writes colour frames (and optionally their depth and the colour
CameraInfo) as a ROS 1 bag (``kind="ros1"``), a ROS 2 bag folder with sqlite3 or MCAP storage
(``"ros2-sqlite3"``, ``"ros2-mcap"``) or a plain ROS 2 MCAP file (``"mcap"``: the file inside
such a folder, moved out), RealSense's topic names by default.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

COLOUR = "/camera/color/image_raw"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/color/camera_info"
FRAME_ID = "camera_color_optical_frame"
T0_NS = 1_700_000_000_123_456_789
PERIOD_NS = 100_000_000  # 10 frames/s


def _store(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _header(T, ros1: bool, stamp_ns: int, seq: int, frame_id: str = FRAME_ID):
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if ros1:
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def colour_message(T, ros1: bool, rgb: np.ndarray, stamp_ns: int, seq: int = 0, compressed: str | None = None,
                   encoding: str = "rgb8"):
    """An Image (``encoding``: rgb8, bgr8, mono8) or CompressedImage (``compressed``: jpeg/png)."""
    header = _header(T, ros1, stamp_ns, seq)
    if compressed is not None:
        _, buf = cv2.imencode(".jpg" if compressed == "jpeg" else ".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        return T["sensor_msgs/msg/CompressedImage"](header=header, format=compressed, data=buf.ravel())
    img = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)}.get(encoding, rgb)
    img = np.ascontiguousarray(img)
    h, w = img.shape[:2]
    return T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                      step=img.strides[0], data=img.reshape(-1).view(np.uint8))


def depth_message(T, ros1: bool, depth_m: np.ndarray, stamp_ns: int, seq: int = 0, compressed: bool = False,
                  encoding: str = "16UC1", frame_id: str = FRAME_ID):
    """A depth Image (16UC1 mm or 32FC1 m) or a compressedDepth PNG (16UC1)."""
    header = _header(T, ros1, stamp_ns, seq, frame_id)
    mm = np.round(np.nan_to_num(depth_m) * 1000).astype(np.uint16)
    if compressed:
        _, buf = cv2.imencode(".png", mm)
        data = np.concatenate([np.zeros(12, np.uint8), buf.ravel()])
        return T["sensor_msgs/msg/CompressedImage"](header=header, format="16UC1; compressedDepth png", data=data)
    img = mm if encoding == "16UC1" else depth_m.astype(np.float32)
    h, w = img.shape
    return T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                      step=img.strides[0], data=np.ascontiguousarray(img).reshape(-1).view(np.uint8))


def info_message(T, ros1: bool, K: np.ndarray, size: tuple[int, int], stamp_ns: int, seq: int = 0,
                 D=(0.0, 0.0, 0.0, 0.0, 0.0), model: str = "plumb_bob"):
    header = _header(T, ros1, stamp_ns, seq)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    fields = {"D": np.asarray(D, float), "K": np.asarray(K, float).ravel(), "R": np.eye(3).ravel(), "P": P.ravel()}
    if not ros1:
        fields = {k.lower(): v for k, v in fields.items()}
    return T["sensor_msgs/msg/CameraInfo"](header=header, height=size[1], width=size[0], distortion_model=model,
                                           binning_x=0, binning_y=0, roi=roi, **fields)


def write_recording(path: Path, kind: str, frames: list[tuple[np.ndarray, np.ndarray | None]], K: np.ndarray,
                    depth: bool = True, info: bool = True, compressed: str | None = None,
                    compressed_depth: bool = False, encoding: str = "rgb8", depth_encoding: str = "16UC1",
                    depth_offset_ns: int = 0, extra: list[tuple[str, object]] = (),
                    colour_topic: str = COLOUR, stamps: list[int] | None = None, info_size: bool = True,
                    depth_topic: str = DEPTH, depth_frame_id: str = FRAME_ID) -> Path:
    """Write ``frames`` ((rgb, depth metres) each) as a recording (module docstring); returns
    the path to give ``infer``. ``K``: (3, 3), or one per frame (each frame's CameraInfo).
    ``extra``: (topic, message-maker(T, ros1, rgb, stamp)) pairs written beside the colour
    topic with every frame (a second colour topic...). ``stamps``: each frame's header stamp
    (default: 10 frames/s from T0_NS; log times stay those); ``info_size``: the CameraInfo
    states the image size (else 0 x 0)."""
    ros1 = kind == "ros1"
    Ks = list(K) if np.ndim(K) == 3 else [K] * len(frames)
    T = _store(ros1).types
    store = _store(ros1)
    topics: dict[str, str] = {}
    messages = []
    for i, (rgb, d) in enumerate(frames):
        log = T0_NS + i * PERIOD_NS
        stamp = log if stamps is None else stamps[i]
        topic = colour_topic + ("/compressed" if compressed else "")
        messages.append((topic, log, colour_message(T, ros1, rgb, stamp, i, compressed, encoding)))
        if depth:
            dt = depth_topic + ("/compressedDepth" if compressed_depth else "")
            messages.append((dt, log + depth_offset_ns, depth_message(T, ros1, d, stamp + depth_offset_ns, i,
                                                                       compressed_depth, depth_encoding,
                                                                       depth_frame_id)))
        if info:
            size = rgb.shape[1::-1] if info_size else (0, 0)
            messages.append((INFO, log, info_message(T, ros1, Ks[i], size, stamp, i)))
        for t, make in extra:
            messages.append((t, log, make(T, ros1, rgb, stamp)))
    messages.sort(key=lambda m: m[1])
    for topic, _, msg in messages:
        topics.setdefault(topic, msg.__msgtype__)
    if ros1:
        from rosbags.rosbag1 import Writer

        with Writer(path) as w:
            conns = {t: w.add_connection(t, mt, typestore=store) for t, mt in topics.items()}
            for topic, stamp, msg in messages:
                w.write(conns[topic], stamp, store.serialize_ros1(msg, msg.__msgtype__))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    folder = path.with_suffix("") if kind == "mcap" else path
    plugin = StoragePlugin.SQLITE3 if kind == "ros2-sqlite3" else StoragePlugin.MCAP
    with Writer(folder, version=9, storage_plugin=plugin) as w:
        conns = {t: w.add_connection(t, mt, typestore=store) for t, mt in topics.items()}
        for topic, stamp, msg in messages:
            w.write(conns[topic], stamp, store.serialize_cdr(msg, msg.__msgtype__))
    if kind == "mcap":
        shutil.move(str(folder / f"{folder.name}.mcap"), str(path))
        shutil.rmtree(folder)
    return path
