"""Atomic writes: write to a temporary file in the target's folder, then rename over it.

A reader never sees a half-written file, and an interrupted job leaves either the old file or
none — so resumable jobs can trust whatever exists. A write that fails (disk full, read-only
file system, name too long...) raises :class:`~dope_hope.errors.OutputPathError` naming the
file and the operating system's reason, and leaves no temporary file behind; a killed process
may leave one, which :func:`remove_stale_temporaries` clears when the job starts again.
"""
from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Callable, Container, Iterator, Mapping
from pathlib import Path
from typing import BinaryIO

from dope_hope.errors import OutputPathError
from dope_hope.io.paths import os_problem

#: Characters of the final stem kept in a temporary name (keeps it within NAME_MAX).
_TMP_STEM_CHARS = 100
#: ``.<stem>.<random>.tmp<suffix>``: the temporary names of :func:`atomic_path`.
_TMP_NAME = re.compile(r"^\.(?P<stem>.+)\.[A-Za-z0-9_]+\.tmp(?P<suffix>\.[^.]*)?$")


def write_error(path: str | os.PathLike, exc: OSError) -> OutputPathError:
    """The one-line error of a failed write of ``path``."""
    if isinstance(exc, IsADirectoryError) or Path(path).is_dir():
        return OutputPathError(path, "is an existing folder; cannot write a file there")
    return OutputPathError(path, f"cannot write ({os_problem(exc)})")


def _make_temporary(path: Path) -> Path:
    """An empty temporary file beside ``path`` (its name keeps the final suffix, so that
    libraries that pick a format from the extension still work: ``.x.abc123.tmp.png``)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:_TMP_STEM_CHARS]}.", suffix=f".tmp{path.suffix}",
                                   dir=path.parent)
    except OSError as exc:
        raise write_error(path, exc) from None
    os.close(fd)
    return Path(tmp)


def _commit(tmp: Path, path: Path) -> None:
    """Give ``tmp`` the permissions of a normal write (mkstemp makes it 0600) and rename it."""
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:
        raise write_error(path, exc) from None


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``.

    An OSError raised while writing becomes an OutputPathError naming ``path``.
    """
    path = Path(path)
    tmp_path = _make_temporary(path)
    try:
        try:
            yield tmp_path
        except OSError as exc:
            raise write_error(path, exc) from None
        _commit(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 text atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_with(path: str | os.PathLike, writer: Callable[[Path], object]) -> None:
    """Call ``writer(tmp_path)`` and move the result to ``path`` atomically."""
    with atomic_path(path) as tmp:
        writer(tmp)


class _RecordingFile:
    """A binary file whose first failed write is kept: libraries that write through a file
    object (``torch.save``) report a full disk as their own RuntimeError, without the errno."""

    def __init__(self, f: BinaryIO):
        self._f = f
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self._f.write(data)
        except OSError as exc:
            self.error = self.error or exc
            raise

    def flush(self) -> None:
        self._f.flush()


def atomic_write_stream(path: str | os.PathLike, writer: Callable[[BinaryIO], object]) -> None:
    """Call ``writer(file)`` with a binary file object and move the result to ``path``
    atomically; a failed write raises OutputPathError with the operating system's reason even
    when ``writer`` wraps it in its own exception."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            rec = _RecordingFile(f)
            try:
                writer(rec)
            except Exception:
                if rec.error is not None:
                    raise rec.error from None
                raise


def atomic_write_files(contents: Mapping[str | os.PathLike, bytes]) -> None:
    """Write several files all or nothing: every temporary file is written first (a full disk
    fails here and changes nothing), then all are renamed into place."""
    written: list[tuple[Path, Path]] = []
    try:
        for path, data in contents.items():
            path = Path(path)
            tmp = _make_temporary(path)
            written.append((tmp, path))
            try:
                tmp.write_bytes(data)
            except OSError as exc:
                raise write_error(path, exc) from None
        for tmp, path in written:
            _commit(tmp, path)
    finally:
        for tmp, _ in written:
            tmp.unlink(missing_ok=True)


def remove_stale_temporaries(folder: str | os.PathLike,
                             stems: Container[str] | Callable[[str], bool]) -> int:
    """Delete the temporary files that killed writers left in ``folder`` for final files whose
    stem is in ``stems`` (or for which ``stems(stem)`` is true); returns how many.

    Only call this when no other process writes those files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    wanted = stems if callable(stems) else stems.__contains__
    removed = 0
    for p in folder.iterdir():
        m = _TMP_NAME.match(p.name)
        if m and wanted(m.group("stem")) and p.is_file():
            p.unlink(missing_ok=True)
            removed += 1
    return removed
