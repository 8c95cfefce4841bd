"""The files a command reads and the files and folders it writes, checked once, before any work.

Every problem is one line naming the path (and the option that gave it): a missing input or
one that is not a regular file (a folder, a named pipe), an output that exists as the wrong
kind of thing, sits on a read-only file system, is not writable, or has a name longer than
the file system allows.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from dope_hope.errors import InputFileError, OutputPathError

#: Folders :func:`output_dir` created since :func:`forget_created_folders`, outermost first
#: (:func:`remove_empty_created_folders` takes back those a failed command left empty).
_CREATED: list[Path] = []

#: What ``path_kind`` calls each kind of file system entry.
_KINDS = ((stat.S_ISDIR, "folder"), (stat.S_ISFIFO, "named pipe"), (stat.S_ISSOCK, "socket"),
          (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"))


def path_kind(path: str | os.PathLike) -> str | None:
    """"file", "folder", "named pipe", "socket", "character device", "block device", or None
    when nothing is there (symbolic links are followed; a dangling one is None)."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            return None
        raise
    if stat.S_ISREG(mode):
        return "file"
    return next((name for test, name in _KINDS if test(mode)), "special file")


def os_problem(exc: OSError) -> str:
    """The operating system's reason in words, e.g. "no space left on device"."""
    text = exc.strerror or str(exc) or type(exc).__name__
    return text[0].lower() + text[1:] if text else text


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    """``path`` as a Path when it is a readable regular file, else InputFileError saying what
    is there instead ("image file not found", "weights file is a named pipe, not a regular
    file")."""
    path = Path(path)
    kind = path_kind(path)
    if kind == "file":
        return path
    if kind is None:
        raise InputFileError(path, f"{what} not found")
    raise InputFileError(path, f"{what} is a {kind}, not a regular file")


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while path_kind(p) is None and p != p.parent:
        p = p.parent
    return p


def _check_writable_folder(folder: Path, target: Path, flag: str | None) -> None:
    """OutputPathError unless new entries can be created in the existing ``folder``."""
    kind = path_kind(folder)
    if kind != "folder":
        raise OutputPathError(target, f"{folder} is a {kind}, not a folder", flag)
    try:
        read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    if read_only:
        raise OutputPathError(target, "on a read-only file system", flag)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(target, f"{folder} is not writable (permission denied)", flag)


def _check_name_lengths(path: Path, existing: Path, flag: str | None) -> None:
    """OutputPathError for a component of ``path`` longer than the file system allows."""
    try:
        limit = os.pathconf(existing, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for part in path.parts:
        size = len(os.fsencode(part))
        if size > limit:
            shown = part if len(part) <= 40 else part[:20] + "..." + part[-12:]
            raise OutputPathError(path, f"file name {shown!r} is {size} bytes, longer than the file "
                                        f"system allows ({limit})", flag)


def output_dir(path: str | os.PathLike, flag: str | None = "--out") -> Path:
    """Create the output folder ``path`` if needed and check that files can be written in it.

    Raises:
        OutputPathError: it exists and is not a folder (or a parent is a file), it is on a
            read-only file system or not writable, a name is too long, or creating it fails.
    """
    path = Path(path)
    kind = path_kind(path)
    if kind not in (None, "folder"):
        raise OutputPathError(path, f"exists and is a {kind}, not a folder", flag)
    existing = path if kind == "folder" else _nearest_existing(path)
    _check_writable_folder(existing, path, flag)
    if kind is None:
        _check_name_lengths(path, existing, flag)
        missing = [p for p in (path.absolute(), *path.absolute().parents)
                   if len(p.parts) > len(existing.parts)][::-1]
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputPathError(path, f"cannot create the folder ({os_problem(exc)})", flag) from None
        _CREATED.extend(missing)
    return path


def forget_created_folders() -> None:
    """Start a new command: the folders created so far are no longer its to take back."""
    _CREATED.clear()


def remove_empty_created_folders() -> None:
    """Remove the folders :func:`output_dir` created that are still empty, deepest first: a
    command that stops on bad input after checking ``--out`` leaves no empty folder behind.
    A folder holding anything, or one that cannot be removed, stays."""
    while _CREATED:
        try:
            _CREATED.pop().rmdir()
        except OSError:
            pass


def output_file(path: str | os.PathLike, flag: str | None = "--out") -> Path:
    """Check that the file ``path`` can be written (created or replaced); creates its folder.

    Raises:
        OutputPathError: it is an existing folder or special file, its folder cannot be made
            or written, or its name is longer than the file system allows.
    """
    path = Path(path)
    kind = path_kind(path)
    if kind == "folder":
        raise OutputPathError(path, "is an existing folder; give a file name", flag)
    if kind not in (None, "file"):
        raise OutputPathError(path, f"exists and is a {kind}, not a regular file", flag)
    parent = path.parent
    if path_kind(parent) not in (None, "folder"):
        raise OutputPathError(path, f"{parent} is a {path_kind(parent)}, not a folder", flag)
    _check_name_lengths(Path(path.name), _nearest_existing(parent), flag)
    try:
        output_dir(parent, None)
    except OutputPathError as exc:
        raise OutputPathError(path, exc.problem, flag) from None
    return path


def weights_format(path: str | os.PathLike) -> str:
    """What a weights file holds, from its first bytes: "torch" (a zip archive: what
    ``torch.save`` writes), "torch-legacy" (a pickle stream: older ``torch.save``), "empty"
    or "other" (an ONNX model, random bytes...)."""
    with open(path, "rb") as f:
        head = f.read(4)
    if not head:
        return "empty"
    if head == b"PK\x03\x04":
        return "torch"
    if head[:1] == b"\x80":
        return "torch-legacy"
    return "other"
