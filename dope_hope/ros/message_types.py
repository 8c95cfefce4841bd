"""The ROS message types of the recordings ``infer`` reads and writes, for ``rosbags``.

:func:`ros2_typestore` is rosbags' ROS 2 Humble store plus two packages it lacks, registered
from their message definitions kept here (:data:`EXTRA_MSG_DEFINITIONS`):

* ``vision_msgs`` (Detection3DArray, Detection3D, ObjectHypothesisWithPose, ObjectHypothesis,
  BoundingBox3D; ROS 2 vision_msgs 4.x), the detections;
* ``foxglove_msgs`` (ImageAnnotations, PointsAnnotation, TextAnnotation, CircleAnnotation,
  Point2, Color), the 2D annotations Foxglove's image panel draws.

The writer embeds each type's definition in the MCAP it writes, so any reader (Foxglove,
``ros2 bag play``, rosbags) decodes them without the packages installed. Reading uses the
definitions a recording embeds; :func:`ros1_typestore` / :func:`ros2_typestore` stand in for
recordings without them. ``rosbags`` is the optional extra ``ros``: :func:`require_rosbags`
turns its absence into one line naming the extra.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any

from dope_hope.errors import ConfigError

#: How a user gets the optional ROS packages (rosbags, foxglove-sdk).
ROS_EXTRA_HINT = 'pip install "dope-hope[ros]"'

#: (type name, .msg text) of the message types the ROS 2 Humble store lacks.
EXTRA_MSG_DEFINITIONS: tuple[tuple[str, str], ...] = (
    ("vision_msgs/msg/ObjectHypothesis", "string class_id\nfloat64 score\n"),
    ("vision_msgs/msg/ObjectHypothesisWithPose",
     "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"),
    ("vision_msgs/msg/BoundingBox3D", "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n"),
    ("vision_msgs/msg/Detection3D",
     "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id\n"),
    ("vision_msgs/msg/Detection3DArray", "std_msgs/Header header\nDetection3D[] detections\n"),
    ("foxglove_msgs/msg/Point2", "float64 x\nfloat64 y\n"),
    ("foxglove_msgs/msg/Color", "float64 r\nfloat64 g\nfloat64 b\nfloat64 a\n"),
    ("foxglove_msgs/msg/CircleAnnotation",
     "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nfloat64 diameter\n"
     "float64 thickness\nfoxglove_msgs/Color fill_color\nfoxglove_msgs/Color outline_color\n"),
    ("foxglove_msgs/msg/PointsAnnotation",
     "uint8 UNKNOWN=0\nuint8 POINTS=1\nuint8 LINE_LOOP=2\nuint8 LINE_STRIP=3\nuint8 LINE_LIST=4\n"
     "builtin_interfaces/Time timestamp\nuint8 type\nfoxglove_msgs/Point2[] points\n"
     "foxglove_msgs/Color outline_color\nfoxglove_msgs/Color[] outline_colors\n"
     "foxglove_msgs/Color fill_color\nfloat64 thickness\n"),
    ("foxglove_msgs/msg/TextAnnotation",
     "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nstring text\nfloat64 font_size\n"
     "foxglove_msgs/Color text_color\nfoxglove_msgs/Color background_color\n"),
    ("foxglove_msgs/msg/ImageAnnotations",
     "foxglove_msgs/CircleAnnotation[] circles\nfoxglove_msgs/PointsAnnotation[] points\n"
     "foxglove_msgs/TextAnnotation[] texts\n"),
)


def require_rosbags() -> None:
    """ConfigError naming the extra to install when ``rosbags`` is missing."""
    try:
        import rosbags  # noqa: F401, PLC0415 (rosbags is the optional ros extra)
    except ModuleNotFoundError as exc:
        if exc.name != "rosbags":
            raise
        raise ConfigError(f"ROS bags and MCAP recordings need the rosbags package: {ROS_EXTRA_HINT}") from None


@lru_cache(maxsize=1)
def ros2_typestore() -> Any:
    """rosbags' ROS 2 Humble typestore with :data:`EXTRA_MSG_DEFINITIONS` registered."""
    require_rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: PLC0415 (rosbags is the optional ros extra)

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in EXTRA_MSG_DEFINITIONS:
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@lru_cache(maxsize=1)
def ros1_typestore() -> Any:
    """rosbags' ROS 1 Noetic typestore (ROS 1 bags without embedded definitions)."""
    require_rosbags()
    from rosbags.typesys import Stores, get_typestore  # noqa: PLC0415 (rosbags is the optional ros extra)

    return get_typestore(Stores.ROS1_NOETIC)
