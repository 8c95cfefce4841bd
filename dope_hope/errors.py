"""The exceptions dope-hope raises for a user's mistake.

Every message names the file (or option) and what is wrong with it, on one line, so that
the CLI can print it as is and exit with status 2.
"""
from __future__ import annotations

import os


class DopeHopeError(Exception):
    """Base class: bad input that the user can fix."""


class InputFileError(DopeHopeError):
    """A file is missing, unreadable or malformed.

    Args:
        path: the offending file.
        problem: what is wrong, e.g. "missing field 'objects[0].location'".
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # picklable across processes (synth workers, DataLoader workers)
        return type(self), (self.path, self.problem)


class UnknownObjectError(DopeHopeError):
    """An object class that is not in the catalog (or not the one a model was trained for)."""


class ConfigError(DopeHopeError):
    """A config file or command-line option is invalid."""


class ModelFileError(InputFileError):
    """A weights file (checkpoint or ONNX) is unreadable or is for another architecture."""


class CameraError(DopeHopeError):
    """No usable camera intrinsics were given or found."""


class OutputPathError(DopeHopeError):
    """An output file or folder cannot be written (exists as the wrong kind, read-only file
    system, name too long, disk full...).

    Args:
        path: the file or folder.
        problem: what is wrong, e.g. "exists and is not a folder".
        flag: the command-line option that named it ("--out"), or None.
    """

    def __init__(self, path: str | os.PathLike, problem: str, flag: str | None = None):
        self.path = str(path)
        self.problem = problem
        self.flag = flag
        super().__init__(f"{flag + ' ' if flag else ''}{self.path}: {problem}")

    def __reduce__(self):
        return type(self), (self.path, self.problem, self.flag)


class DeviceError(DopeHopeError):
    """A camera cannot be opened, or stopped delivering frames."""
