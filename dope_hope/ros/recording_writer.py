"""Write ROS 2 messages as a recording: a ROS 2 bag folder with MCAP storage, by ``rosbags``'
writer (what ``ros2 bag play FOLDER`` plays and Foxglove opens as ``FOLDER/FOLDER.mcap``).

:class:`RecordingWriter` writes into a temporary folder beside the target and renames it into
place on :meth:`~RecordingWriter.close`; :meth:`~RecordingWriter.discard` (or an error) leaves
nothing, so a reader never sees half a recording. Each topic's connection is added on its
first message with the type's definition embedded (readers need no ROS packages); messages
are stored on the log time the caller gives (the image's stamp).
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from dope_hope.io.atomic import write_error
from dope_hope.ros.message_types import require_rosbags, ros2_typestore


class RecordingWriter:
    """A ROS 2 MCAP bag written atomically (module docstring).

    Args:
        path: the bag folder to create (replaced on close when it exists); its MCAP file is
            ``path/<folder name>.mcap``.
    """

    def __init__(self, path: str | os.PathLike):
        require_rosbags()
        from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: PLC0415 (rosbags is the optional ros extra)

        self.path = Path(path)
        self.store = ros2_typestore()
        self.counts: dict[str, int] = {}
        self._connections: dict[str, Any] = {}
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name[:100]}.", suffix=".tmp", dir=self.path.parent))
            self._writer = Writer(self._tmp / self.path.name, version=9, storage_plugin=StoragePlugin.MCAP)
            self._writer.open()
        except OSError as exc:
            self._cleanup()
            raise write_error(self.path, exc) from None

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Store ``msg`` (a typestore message of :func:`ros2_typestore`) on ``topic`` at ``stamp_ns``."""
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msg.__msgtype__, typestore=self.store)
            self._connections[topic] = conn
        try:
            self._writer.write(conn, int(stamp_ns), bytes(self.store.serialize_cdr(msg, msg.__msgtype__)))
        except OSError as exc:
            self.discard()
            raise write_error(self.path, exc) from None
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> Path:
        """Finish the bag and move it into place; returns its folder."""
        try:
            self._writer.close()
            if self.path.is_dir():
                shutil.rmtree(self.path)
            elif self.path.exists():
                self.path.unlink()
            os.replace(self._tmp / self.path.name, self.path)
        except OSError as exc:
            self._cleanup()
            raise write_error(self.path, exc) from None
        self._cleanup()
        return self.path

    def discard(self) -> None:
        """Drop what was written (idempotent)."""
        writer = getattr(self, "_writer", None)
        if writer is not None and writer.storage is not None:
            try:
                writer.storage.abort()
            except Exception:  # noqa: BLE001 - best effort before the folder goes
                pass
        self._cleanup()

    def _cleanup(self) -> None:
        tmp = getattr(self, "_tmp", None)
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
            self._tmp = None
