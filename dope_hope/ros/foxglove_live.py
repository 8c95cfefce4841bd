"""Live results for the Foxglove app: a WebSocket server (Foxglove's protocol, ``foxglove-sdk``)
serving the messages of :mod:`dope_hope.ros.pose_messages` as they are made.

Each topic of :data:`~dope_hope.ros.pose_messages.TOPICS` is a channel with the type's
``ros2msg`` definition as schema and CDR messages: the very bytes the output MCAP stores, so
Foxglove shows the image, the image annotations, the cuboid markers (a 3D scene in the camera
frame), the poses and tf as it does for a ROS 2 robot. :meth:`FoxgloveLive.wait_for_client`
holds a file's playback until the app subscribes (a live camera does not wait).
"""
from __future__ import annotations

import threading
from typing import Any

from dope_hope.errors import ConfigError, DeviceError
from dope_hope.ros.defaults import DEFAULT_FOXGLOVE_PORT
from dope_hope.ros.message_types import ROS_EXTRA_HINT
from dope_hope.ros.pose_messages import TOPICS, PoseMessages


def _import_foxglove():
    try:
        import foxglove  # noqa: PLC0415 (foxglove-sdk is the optional ros extra)
    except ModuleNotFoundError as exc:
        if exc.name != "foxglove":
            raise
        raise ConfigError(f"--foxglove needs the foxglove-sdk package: {ROS_EXTRA_HINT}") from None
    return foxglove


def _subscription_listener(fg, subscribed: threading.Event):
    """A foxglove ServerListener that sets ``subscribed`` on a client's first subscription."""

    class Subscriptions(fg.websocket.ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            subscribed.set()

    return Subscriptions()


class FoxgloveLive:
    """A Foxglove WebSocket server on ``host:port`` (0: a free port; :attr:`port` says which)."""

    def __init__(self, port: int = DEFAULT_FOXGLOVE_PORT, host: str = "127.0.0.1", messages: PoseMessages | None = None):
        fg = _import_foxglove()
        self.messages = messages or PoseMessages()
        self.context = fg.Context()
        self.subscribed = threading.Event()
        try:
            self.server = fg.start_server(name="dope-hope", host=host, port=int(port), context=self.context,
                                          server_listener=_subscription_listener(fg, self.subscribed))
        except Exception as exc:  # noqa: BLE001 - the SDK reports a taken port as a plain error
            raise DeviceError(f"--foxglove {port}: cannot serve on {host}:{port} ({exc})") from None
        self.host = host
        self.port = int(self.server.port)
        self.channels = {}
        for topic, msgtype in TOPICS.items():
            schema = fg.Schema(name=msgtype, encoding="ros2msg",
                               data=self.messages.definition(msgtype).encode("utf-8"))
            self.channels[topic] = fg.Channel(topic, schema=schema, message_encoding="cdr", context=self.context)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def wait_for_client(self, timeout_s: float | None = None) -> bool:
        """Block until a client subscribes to a channel (or ``timeout_s`` passes); True if one did."""
        return self.subscribed.wait(timeout_s)

    def publish(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Send ``msg`` on ``topic`` to the subscribed clients, logged at ``stamp_ns``."""
        self.channels[topic].log(self.messages.serialize(msg), log_time=int(stamp_ns))

    def close(self) -> None:
        """Stop the server (idempotent)."""
        server, self.server = getattr(self, "server", None), None
        if server is not None:
            for ch in self.channels.values():
                ch.close()
            server.stop()
