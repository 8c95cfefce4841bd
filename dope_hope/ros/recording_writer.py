"""Write ROS 2 messages as a recording: a ROS 2 bag folder with MCAP storage, by ``rosbags``'
writer (what ``ros2 bag play FOLDER`` plays and Foxglove opens as ``FOLDER/FOLDER.mcap``).

:class:`RecordingWriter` writes into a temporary folder beside the target and renames it into
place on :meth:`~RecordingWriter.close`; :meth:`~RecordingWriter.discard` (or an error) leaves
nothing, so a reader never sees half a recording. An existing folder is replaced only when
it holds nothing but such a bag (its ``metadata.yaml`` and MCAP file): a folder holding
anything else is refused before any work. Each topic's connection is added on its
first message with the type's definition embedded (readers need no ROS packages); messages
are stored on the log time the caller gives (the image's stamp).
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from dope_hope.errors import OutputPathError
from dope_hope.io.atomic import write_error
from dope_hope.ros.message_types import require_rosbags, ros2_typestore


def check_replaceable_bag(path: Path) -> None:
    """OutputPathError unless ``path`` is absent, or a folder holding only what a bag written
    here holds (``metadata.yaml``, ``<folder name>.mcap``): a user's files are never replaced."""
    if not path.is_dir():
        return
    bag = {"metadata.yaml", f"{path.name}.mcap"}
    other = sorted(p.name for p in path.iterdir() if p.name not in bag or not p.is_file())
    if other:
        raise OutputPathError(path, f"holds {other[0]}" + (f" and {len(other) - 1} more" if len(other) > 1 else "")
                              + ", which a poses bag does not: not replaced (another --out, or move it away)")


class RecordingWriter:
    """A ROS 2 MCAP bag written atomically (module docstring).

    Args:
        path: the bag folder to create (replaced on close when it holds only a bag); its MCAP file is
            ``path/<folder name>.mcap``.
    """

    def __init__(self, path: str | os.PathLike):
        require_rosbags()
        from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: PLC0415 (rosbags is the optional ros extra)

        self.path = Path(path)
        check_replaceable_bag(self.path)
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
