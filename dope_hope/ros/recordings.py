"""Robot recordings as a frame source: ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and
plain ROS 2 MCAP files, read with ``rosbags`` (pure Python; no ROS installation).

:func:`~dope_hope.io.streams.is_recording` tells a recording input (``NAME.bag``, ``NAME.mcap``, ``NAME.db3``, or a
ROS 2 bag folder holding ``metadata.yaml``); :class:`RecordingSource` plays one as a
:class:`~dope_hope.io.streams.FrameSource`, so ``infer`` runs it through the same stream loop
as a video.

**Topics** (:func:`choose_topics`): the colour image (``sensor_msgs/Image`` or
``CompressedImage``), a depth image registered to it and the colour ``CameraInfo``. Named by
the caller, or chosen when unambiguous: the colour topic is the one image topic whose name
holds neither "depth" nor "infra" (a topic and its ``/compressed`` twin count as one, the raw
image preferred; RealSense's ``.../color/image_raw``); the depth topic the one with "depth" in
its name ("aligned_depth_to_color" preferred); camera_info the colour topic's sibling
``.../camera_info``, else the only CameraInfo topic.

**Messages** (:func:`decode_image`, :func:`decode_depth`): Image rgb8, rgba8, bgr8, bgra8,
mono8; depth Image 16UC1 / mono16 (millimetres) and 32FC1 (metres, NaN = no measurement);
CompressedImage jpeg / png (colour), ``compressedDepth`` png (16UC1 millimetres, 32FC1 inverse
depth as ``image_transport``'s compressed_depth plugin writes it). Anything else is refused
with the topic named.

**Camera**: each colour image is read with the CameraInfo of its own header stamp, as
``image_transport`` pairs them (:class:`~dope_hope.ros.camera_pairing.CameraByStamp`: a recording
of one camera needs no equal stamps; a camera that changes needs them); width and height are
checked against the images (an info without a size: every image paired with it has the size of
the first); a distorted camera (non-zero D, plumb_bob or rational_polynomial) is undistorted as
``image_proc`` does (:class:`~dope_hope.io.camera.Rectification`, depth with it), other
distortion models are refused: never treated as pinhole. A camera given by the caller
(``--camera``) replaces it.

**Depth pairing**: each colour frame takes the depth message whose header stamp is nearest to
its own, within ``tolerance_s`` (:data:`DEFAULT_SYNC_TOLERANCE_S`), one not yet paired first:
colour frames that share a stamp (every stamp 0 in a converted recording) take the depth
messages of that stamp in recorded order, and one warning says so; a depth image that a second
colour frame of its stamp has to take again is counted in that warning. A colour frame inside the
depth stream's span without one is an error (the recording's streams are out of step); colour
frames before the first depth message or after the last are processed without depth and
counted in one warning. The depth topic must be registered to colour: a chosen depth topic
whose header ``frame_id`` is not the colour image's is refused (``--depth-topic`` names one
anyway, with a warning).

Each :class:`~dope_hope.io.streams.Frame` carries the colour header's stamp (``stamp_ns``) and
``frame_id``; ``timestamp_s`` is the stamp minus the first frame's. Frames are named after the
recording's file or folder (``infer .`` inside a bag folder: the folder's own name).
"""
from __future__ import annotations

import collections
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dope_hope.errors import CameraError, ConfigError, InputFileError
from dope_hope.io.camera import ImageCamera, Rectification, parse_ros_camera_info
from dope_hope.io.streams import Frame, FrameSource, Grabbed
from dope_hope.ros.camera_pairing import CameraByStamp, single_camera
from dope_hope.ros.defaults import DEFAULT_SYNC_TOLERANCE_S
from dope_hope.ros.message_types import require_rosbags, ros1_typestore, ros2_typestore

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED)
#: Colour encodings of sensor_msgs/Image: (channels, OpenCV conversion to RGB or None).
COLOUR_ENCODINGS = {"rgb8": 3, "rgba8": 4, "bgr8": 3, "bgra8": 4, "mono8": 1}
#: Depth encodings of sensor_msgs/Image and their metres per unit (32FC1: metres).
DEPTH_ENCODINGS = {"16UC1": 0.001, "mono16": 0.001, "32FC1": 1.0}


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


# ----------------------------------------------------------------------------- decoding
def decode_image(msg: Any, where: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour Image or CompressedImage message; InputFileError
    naming ``where`` (file and topic) for an encoding it does not take."""
    if msg.__msgtype__ == COMPRESSED:
        fmt = msg.format.lower()
        if "compresseddepth" in fmt or not any(k in fmt for k in ("jpeg", "jpg", "png")):
            raise InputFileError(where, f"CompressedImage format {msg.format!r} is not a colour image "
                                        "(jpeg or png expected)")
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.dtype != np.uint8:
            raise InputFileError(where, f"CompressedImage ({msg.format}) cannot be decoded as an 8-bit image")
        if img.ndim == 2:
            return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    enc = msg.encoding
    if enc not in COLOUR_ENCODINGS:
        raise InputFileError(where, f"Image encoding {enc!r} is not supported for colour "
                                    f"({', '.join(COLOUR_ENCODINGS)})")
    ch = COLOUR_ENCODINGS[enc]
    img = _pixels(msg, np.uint8, ch, where)
    if enc == "mono8":
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    code = {"rgba8": cv2.COLOR_RGBA2RGB, "bgr8": cv2.COLOR_BGR2RGB, "bgra8": cv2.COLOR_BGRA2RGB}.get(enc)
    return np.ascontiguousarray(img) if code is None else cv2.cvtColor(img, code)


def _pixels(msg: Any, dtype: Any, channels: int, where: str) -> np.ndarray:
    """The (H, W[, C]) pixels of an Image message (row stride ``step``, byte order checked)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize * channels
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if h < 1 or w < 1 or step < w * item or data.size < h * step:
        raise InputFileError(where, f"Image {w}x{h} with step {step} holds {data.size} bytes: truncated or malformed")
    rows = data[: h * step].reshape(h, step)[:, : w * item]
    arr = rows.copy().view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    arr = arr.astype(np.dtype(dtype).newbyteorder("="), copy=False)
    return arr.reshape(h, w, channels) if channels > 1 else arr.reshape(h, w)


def decode_depth(msg: Any, where: str) -> np.ndarray:
    """(H, W) float32 metres (0 = no measurement) of a depth Image or compressedDepth message."""
    if msg.__msgtype__ == COMPRESSED:
        fmt = msg.format
        if "compressedDepth" not in fmt or "rvl" in fmt.lower():
            raise InputFileError(where, f"CompressedImage format {fmt!r} is not a supported depth image "
                                        "(compressedDepth png expected)")
        raw = bytes(msg.data)
        # compressed_depth_image_transport: a 12-byte header (int32 format, float32 depthQuantA, B), then PNG
        png = cv2.imdecode(np.frombuffer(raw[12:], np.uint8), cv2.IMREAD_UNCHANGED) if len(raw) > 12 else None
        if png is None or png.ndim != 2 or png.dtype != np.uint16:
            raise InputFileError(where, f"compressedDepth ({fmt}) cannot be decoded as a 16-bit PNG")
        if fmt.startswith("32FC1"):
            quant_a, quant_b = np.frombuffer(raw[4:12], "<f4")
            inv = png.astype(np.float32)
            out = np.zeros_like(inv)
            ok = png > 0
            out[ok] = quant_a / (inv[ok] - quant_b)
            return np.where(np.isfinite(out) & (out > 0), out, 0).astype(np.float32)
        if fmt.startswith("16UC1") or fmt.startswith("mono16"):
            return png.astype(np.float32) * np.float32(0.001)
        raise InputFileError(where, f"compressedDepth format {fmt!r}: 16UC1 or 32FC1 expected")
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise InputFileError(where, f"Image encoding {enc!r} is not supported for depth "
                                    f"({', '.join(DEPTH_ENCODINGS)})")
    arr = _pixels(msg, np.float32 if enc == "32FC1" else np.uint16, 1, where).astype(np.float32)
    arr *= np.float32(DEPTH_ENCODINGS[enc])
    arr[~np.isfinite(arr) | (arr < 0)] = 0
    return arr


def _info_fields(msg: Any) -> dict[str, Any]:
    """The fields of a CameraInfo message that make its camera (ROS 2 names k, d, r, p; ROS 1 K, D, R, P)."""
    def field(name: str) -> list:
        value = getattr(msg, name, None)
        return [float(v) for v in (getattr(msg, name.upper()) if value is None else value)]

    return {"k": field("k"), "d": field("d"), "r": field("r"), "p": field("p"),
            "width": int(msg.width) or None, "height": int(msg.height) or None,
            "distortion_model": msg.distortion_model or "plumb_bob"}


def info_key(msg: Any) -> tuple:
    """What tells two CameraInfo messages' cameras apart (equal keys: one camera)."""
    return tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in _info_fields(msg).items())


def camera_from_info(msg: Any, where: str) -> tuple[np.ndarray, int | None, int | None, Rectification | None]:
    """(K of the frames, width, height, rectification or None) of a CameraInfo message:
    :func:`~dope_hope.io.camera.parse_ros_camera_info` on its fields (a distortion model
    OpenCV does not undistort is refused there)."""
    data = _info_fields(msg)
    if not np.any(data["r"]):
        data["r"] = None  # unset (all zero): the identity
    if not np.any(data["p"]):
        data["p"] = None
    return parse_ros_camera_info(data, where)


# ----------------------------------------------------------------------------- topics
@dataclass
class TopicInfo:
    """One topic of a recording: name, message type, message count."""

    name: str
    msgtype: str
    count: int


@dataclass
class Topics:
    """The topics a recording is played with: colour (required), depth and camera_info (or None)."""

    image: str
    depth: str | None
    camera_info: str | None


def _base(name: str) -> str:
    for tail in ("/compressedDepth", "/compressed"):
        if name.endswith(tail):
            return name[: -len(tail)]
    return name


def _one_per_base(names: list[str], types: dict[str, str]) -> list[str]:
    """Collapse a topic and its ``/compressed`` twin into one, the raw Image preferred."""
    by_base: dict[str, list[str]] = collections.defaultdict(list)
    for n in names:
        by_base[_base(n)].append(n)
    return sorted(min(group, key=lambda n: (types[n] != IMAGE, n)) for group in by_base.values())


def choose_topics(path: str | os.PathLike, topics: dict[str, TopicInfo], image: str | None = None,
                  depth: str | None = None, camera_info: str | None = None) -> Topics:
    """The colour, depth and camera_info topics (module docstring). ``depth="none"`` plays
    without depth. ConfigError naming the flag and the recording's topics when a topic is
    missing, of the wrong type, or ambiguous."""
    types = {t.name: t.msgtype for t in topics.values()}
    images = [n for n, t in types.items() if t in IMAGE_TYPES]
    infos = [n for n, t in types.items() if t == CAMERA_INFO]

    def named(flag: str, name: str, allowed: tuple[str, ...]) -> str:
        if name not in types:
            raise ConfigError(f"{flag} {name}: no such topic in {path} (its topics: {', '.join(sorted(types)) or 'none'})")
        if types[name] not in allowed:
            raise ConfigError(f"{flag} {name}: a {types[name]} topic in {path}, not {' or '.join(allowed)}")
        return name

    def lower(n: str) -> str:
        return n.lower()

    if image is not None:
        image = named("--image-topic", image, IMAGE_TYPES)
    else:
        colour = _one_per_base([n for n in images if "depth" not in lower(n) and "infra" not in lower(n)], types)
        if not colour:
            raise ConfigError(f"{path}: no colour image topic (sensor_msgs/Image or CompressedImage) "
                              f"among {', '.join(sorted(types)) or 'no topics'}")
        if len(colour) > 1:
            raise ConfigError(f"{path}: several colour image topics ({', '.join(colour)}); "
                              "name one with --image-topic")
        image = colour[0]
    if depth == "none":
        depth = None
    elif depth is not None:
        depth = named("--depth-topic", depth, IMAGE_TYPES)
    else:
        depths = _one_per_base([n for n in images if "depth" in lower(n)], types)
        aligned = [n for n in depths if "aligned" in lower(n)]
        depths = aligned or depths
        if len(depths) > 1:
            raise ConfigError(f"{path}: several depth image topics ({', '.join(depths)}); name one with "
                              "--depth-topic (or --depth-topic none)")
        depth = depths[0] if depths else None
    if camera_info is not None:
        camera_info = named("--camera-info-topic", camera_info, (CAMERA_INFO,))
    else:
        sibling = _base(image).rsplit("/", 1)[0] + "/camera_info"
        colour_infos = [n for n in infos if "depth" not in lower(n) and "infra" not in lower(n)]
        camera_info = sibling if sibling in infos else (colour_infos[0] if len(colour_infos) == 1 else None)
    return Topics(image, depth, camera_info)


# ----------------------------------------------------------------------------- the source
def _corrupt(path: Path, exc: BaseException) -> InputFileError:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return InputFileError(path, f"not a readable ROS bag / MCAP recording ({text})")


def _open_reader(path: Path) -> Any:
    """An open rosbags AnyReader of ``path``; InputFileError for a missing or unreadable one."""
    require_rosbags()
    from rosbags.highlevel import AnyReader  # noqa: PLC0415 (rosbags is the optional ros extra)

    if not path.exists():
        raise InputFileError(path, "recording not found")
    try:
        reader = AnyReader([path], default_typestore=ros1_typestore() if path.suffix == ".bag" else ros2_typestore())
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds for a bad file
        raise _corrupt(path, exc) from None
    return reader


def _topic_infos(reader: Any) -> dict[str, TopicInfo]:
    return {name: TopicInfo(name, info.msgtype or "?", int(info.msgcount)) for name, info in reader.topics.items()}


def topic_table(path: str | os.PathLike, image_topic: str | None = None, depth_topic: str | None = None,
                camera_info_topic: str | None = None) -> str:
    """The recording's topics (name, type, message count), the ones :func:`choose_topics` picks
    marked; when it cannot pick, its reason on the last line (``infer --list-topics``)."""
    path = Path(path)
    reader = _open_reader(path)
    try:
        topics = _topic_infos(reader)
    finally:
        reader.close()
    note = ""
    try:
        chosen = choose_topics(path, topics, image_topic, depth_topic, camera_info_topic)
        roles = {chosen.image: "colour", chosen.depth: "depth", chosen.camera_info: "camera_info"}
    except ConfigError as exc:
        roles, note = {}, f"\n  no choice: {exc}"
    width = max((len(n) for n in topics), default=0)
    lines = [f"{path}: {len(topics)} topic(s)"]
    for t in sorted(topics.values(), key=lambda t: t.name):
        role = f"  <- {roles[t.name]}" if t.name in roles else ""
        lines.append(f"  {t.name:<{width}}  {t.msgtype}  {t.count} message(s){role}")
    return "\n".join(lines) + note


class RecordingSource(FrameSource):
    """The colour frames of a recording, with their paired depth and camera.

    Args:
        path: the recording (module docstring).
        image_topic, depth_topic, camera_info_topic: as :func:`choose_topics`.
        camera: intrinsics given by the caller (replace the recording's CameraInfo), or None.
        tolerance_s: largest colour-to-depth stamp difference of a pair, seconds.
        warn: told (one line each) how many colour frames were processed without depth, what
            shared stamps made of the pairing, and a named depth topic of another frame.
    """

    def __init__(self, path: str | os.PathLike, image_topic: str | None = None, depth_topic: str | None = None,
                 camera_info_topic: str | None = None, camera: ImageCamera | None = None,
                 tolerance_s: float = DEFAULT_SYNC_TOLERANCE_S, warn: Callable[[str], None] | None = None):
        self.path = Path(path)
        self.name = recording_name(self.path)
        self.tolerance_ns = round(tolerance_s * 1e9)
        self.warn = warn
        self._reader = _open_reader(self.path)
        try:
            self.topics = _topic_infos(self._reader)
            self.chosen = choose_topics(self.path, self.topics, image_topic, depth_topic, camera_info_topic)
            self.length = self.topics[self.chosen.image].count or None
            self.cameras = single_camera(str(camera.source), camera) if camera is not None else self._recorded_cameras()
            self._check_first_messages(depth_named=depth_topic not in (None, "none"))
        except BaseException:
            self.close()
            raise

    def _messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, message) of ``topics``, in log-time order."""
        conns = [c for c in self._reader.connections if c.topic in topics]
        try:
            for conn, t, raw in self._reader.messages(connections=conns):
                yield conn.topic, t, self._reader.deserialize(raw, conn.msgtype)
        except InputFileError:
            raise
        except Exception as exc:  # noqa: BLE001 - a truncated or corrupt chunk / record
            raise _corrupt(self.path, exc) from None

    def _where(self, topic: str) -> str:
        return f"{self.path} topic {topic}"

    def _recorded_cameras(self) -> CameraByStamp[ImageCamera]:
        """Every CameraInfo message of the chosen topic by its stamp (module docstring)."""
        topic = self.chosen.camera_info
        if topic is None:
            raise CameraError(f"{self.path}: no camera_info topic for {self.chosen.image}; name one with "
                              "--camera-info-topic, or give --camera K.json|camera_info.yaml")
        where = self._where(topic)
        cameras: CameraByStamp[ImageCamera] = CameraByStamp(where)

        def make(msg: Any) -> Callable[[], ImageCamera]:
            def camera() -> ImageCamera:
                K, width, height, rect = camera_from_info(msg, where)
                return ImageCamera(K=K, width=width, height=height, source=Path(where), rectification=rect)
            return camera

        for _, _, msg in self._messages([topic]):
            cameras.add(_stamp_ns(msg), info_key(msg), make(msg))
        if not len(cameras):
            raise CameraError(f"{where}: holds no CameraInfo message; give --camera")
        return cameras

    def _check_first_messages(self, depth_named: bool) -> None:
        """Decode the first colour and depth messages, so that an encoding this reader does not
        take, a camera of another size, depth of another size or frame than colour is
        reported before any work; ``self.camera``: the first colour frame's camera."""
        first = {}
        for topic, decode in ((self.chosen.image, decode_image), (self.chosen.depth, decode_depth)):
            if topic is not None:
                msg = next((m for _, _, m in self._messages([topic])), None)
                if msg is None:
                    raise InputFileError(self.path, f"{topic}: holds no message")
                first[topic] = (msg, decode(msg, self._where(topic)))
        msg, rgb = first[self.chosen.image]
        self.camera = self.cameras.camera_for(_stamp_ns(msg))
        self.camera.check_size(self._where(self.chosen.image), rgb.shape[1], rgb.shape[0])
        if self.chosen.depth is None:
            return
        depth_msg, depth = first[self.chosen.depth]
        if depth.shape != rgb.shape[:2]:
            raise InputFileError(self._where(self.chosen.depth), _not_registered(
                f"its images are {depth.shape[1]}x{depth.shape[0]}, the colour images {rgb.shape[1]}x{rgb.shape[0]}"))
        colour_frame, depth_frame = str(msg.header.frame_id), str(depth_msg.header.frame_id)
        if colour_frame != depth_frame:
            problem = f"its frame_id is {depth_frame!r}, the colour images' {colour_frame!r}"
            if not depth_named:
                raise InputFileError(self._where(self.chosen.depth), _not_registered(problem))
            if self.warn is not None:
                self.warn(f"{self._where(self.chosen.depth)}: {problem}; used as registered to colour because "
                          "--depth-topic names it")

    def grab(self) -> Iterator[Grabbed]:
        chosen, tol = self.chosen, self.tolerance_ns
        topics = [chosen.image] + ([chosen.depth] if chosen.depth else [])
        pending: collections.deque = collections.deque()  # colour (stamp, msg) awaiting depth
        depths: list[list] = []  # [stamp, msg, times paired], stamps increasing
        first_depth: int | None = None
        state = {"index": 0, "t0": None, "unpaired": 0, "reused": 0}
        stamps = StampTies()

        def emit(stamp: int, msg: Any, depth_msg: Any) -> Grabbed:
            index = state["index"]
            state["index"] += 1
            state["t0"] = stamp if state["t0"] is None else state["t0"]
            ts = (stamp - state["t0"]) / 1e9
            return Grabbed(index, ts, lambda: self._frame(index, ts, stamp, msg, depth_msg))

        def pair(stamp: int, msg: Any, final: bool) -> Grabbed:
            # nearest stamp first; among equally near ones, one not yet paired, the earliest
            near = min(depths, key=lambda d: (abs(d[0] - stamp), d[2] > 0), default=None)
            if near is not None and abs(near[0] - stamp) <= tol:
                state["reused"] += near[2] > 0 and near[0] == stamp
                near[2] += 1
                return emit(stamp, msg, near[1])
            outside = first_depth is None or stamp < first_depth - tol or (final and stamp > depths[-1][0] + tol)
            if not outside:
                gap = "none" if near is None else f"{abs(near[0] - stamp) / 1e6:.1f} ms"
                raise InputFileError(self.path, f"{chosen.depth}: no depth message within {tol / 1e6:g} ms of the "
                                                f"{chosen.image} frame stamped {stamp / 1e9:.6f} s (nearest: {gap}); "
                                                "the streams are out of step (--sync-tolerance MS, or --depth-topic none)")
            state["unpaired"] += 1
            return emit(stamp, msg, None)

        def exact_unpaired(stamp: int) -> bool:
            return any(d[0] == stamp and not d[2] for d in depths)

        for topic, _, msg in self._messages(topics):
            stamp = _stamp_ns(msg)
            if topic == chosen.image:
                stamps.add(stamp)
            if topic == chosen.image and chosen.depth is None:
                yield emit(stamp, msg, None)
                continue
            if topic == chosen.image:
                pending.append((stamp, msg))
            else:
                first_depth = stamp if first_depth is None else first_depth
                depths.append([stamp, msg, 0])
            while pending and depths and (depths[-1][0] > pending[0][0] + tol or exact_unpaired(pending[0][0])):
                yield pair(*pending.popleft(), final=False)
                # drop what no colour frame still to come can take: depth older than the next
                # colour frame's window, and a paired one with a later one of its stamp
                keep_from = pending[0][0] - tol if pending else None
                depths[:] = [d for i, d in enumerate(depths)
                             if not (keep_from is not None and d[0] < keep_from and i < len(depths) - 1)
                             and not (d[2] and any(e[0] == d[0] for e in depths[i + 1:]))]
        while pending:
            yield pair(*pending.popleft(), final=True)
        if self.warn is not None:
            if state["unpaired"] and chosen.depth:
                self.warn(f"{self.path}: {state['unpaired']} colour frame(s) before the first or after the last "
                          f"{chosen.depth} message were processed without depth")
            tie = stamps.describe(chosen.image, chosen.depth, state["reused"])
            if tie:
                self.warn(f"{self.path}: {tie}")
        if state["index"] == 0:
            raise InputFileError(self.path, f"{chosen.image}: no message could be read")

    def _frame(self, index: int, timestamp_s: float, stamp: int, msg: Any, depth_msg: Any) -> Frame:
        rgb = decode_image(msg, self._where(self.chosen.image))
        name = f"{self.name}#{index:06d}"
        camera = self.cameras.camera_for(stamp)
        where = f"{self._where(self.chosen.image)} ({name})"
        camera.check_size(where, rgb.shape[1], rgb.shape[0])
        stated = None if camera.width is None or camera.height is None else (camera.width, camera.height)
        self.cameras.check_image_size(stamp, rgb.shape[1], rgb.shape[0], name, stated)
        depth = None
        if depth_msg is not None:
            depth = decode_depth(depth_msg, self._where(self.chosen.depth))
            if depth.shape != rgb.shape[:2]:
                raise InputFileError(self._where(self.chosen.depth), _not_registered(
                    f"its image is {depth.shape[1]}x{depth.shape[0]}, the colour image {name} "
                    f"{rgb.shape[1]}x{rgb.shape[0]}"))
        rect = camera.rectification
        if rect is not None:
            rgb = rect.image(rgb)
            depth = None if depth is None else rect.depth(depth)
        return Frame(index=index, timestamp_s=timestamp_s, name=name, rgb=rgb, K=camera.K, depth=depth,
                     stamp_ns=stamp, frame_id=str(msg.header.frame_id))

    def close(self) -> None:
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a reader that failed midway
                pass


def recording_name(path: Path) -> str:
    """The name of a recording's frames and outputs: its file or folder name (``.`` inside a
    bag folder: that folder's name)."""
    return path.name or path.resolve().name or str(path)


def _not_registered(problem: str) -> str:
    return (f"not registered to colour ({problem}); name a depth topic aligned to colour with --depth-topic "
            "(RealSense: align_depth), or --depth-topic none")


class StampTies:
    """The colour stamps of a recording seen so far, and what their ties did to the pairing."""

    def __init__(self) -> None:
        self.count = 0
        self.first: int | None = None
        self.all_equal = True
        self.repeats = 0
        self.first_repeat: int | None = None
        self._last_seen: set[int] = set()

    def add(self, stamp: int) -> None:
        self.count += 1
        self.first = stamp if self.first is None else self.first
        self.all_equal = self.all_equal and stamp == self.first
        if stamp in self._last_seen:
            self.repeats += 1
            self.first_repeat = stamp if self.first_repeat is None else self.first_repeat
        self._last_seen.add(stamp)

    def describe(self, image: str, depth: str | None, reused: int) -> str:
        """One sentence for the warning ("" when every stamp is unique)."""
        if not self.repeats:
            return ""
        paired = "" if depth is None else f", paired with {depth} in recorded order"
        again = "" if not reused else f"; {reused} of them took a depth image already paired with another frame"
        if self.all_equal:
            return (f"every {image} message has the header stamp {self.first / 1e9:.6f} s: the frames are "
                    f"taken in recorded order{paired}{again}")
        return (f"{self.repeats} {image} message(s) repeat an earlier header stamp (first: "
                f"{self.first_repeat / 1e9:.6f} s){paired}{again}")


def open_recording(inputs: list[str], image_topic: str | None = None, depth_topic: str | None = None,
                   camera_info_topic: str | None = None, camera: ImageCamera | None = None,
                   depth: str | None = None, tolerance_s: float = DEFAULT_SYNC_TOLERANCE_S,
                   icp: bool = False, warn: Callable[[str], None] | None = None) -> RecordingSource:
    """The one recording ``inputs`` names, as ``infer`` plays it: ConfigError for other inputs
    beside it, for ``--depth`` (a recording brings its own) and for ``icp`` without a depth topic."""
    if len(inputs) != 1:
        raise ConfigError(f"{inputs[0]}: a recording must be the only input")
    if depth is not None:
        raise ConfigError(f"--depth applies to image inputs; the recording {inputs[0]} brings its own (--depth-topic)")
    source = RecordingSource(inputs[0], image_topic, depth_topic, camera_info_topic, camera, tolerance_s, warn)
    if icp and source.chosen.depth is None:
        source.close()
        raise ConfigError(f"--icp refines against a depth image: {source.name} has no depth topic to use "
                          "(name one with --depth-topic)")
    return source
