"""``dope-hope``: the command-line entry point.

Each subcommand lives in ``dope_hope/commands/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports (torch, pyrender) happen inside ``run`` so that
``dope-hope --help`` stays fast. A :class:`DopeHopeError`, a bad option value and an
unwritable output (disk full...) are printed on one line and the process exits with status 2;
warnings print one line each; Ctrl-C exits 130, SIGTERM 143, after the command's cleanup
(an output folder it created and left empty is removed).
"""
from __future__ import annotations

import argparse
import contextlib
import contextvars
import errno
import importlib
import signal
import sys
import warnings
from collections.abc import Iterator

from dope_hope import __version__
from dope_hope.errors import DopeHopeError
from dope_hope.io.paths import forget_created_folders, remove_empty_created_folders

#: (subcommand, module under dope_hope.commands, one-line help)
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("objects", "objects", "list the 28 HOPE objects"),
    ("train", "train", "train a network for one object on DOPE-format folders"),
    ("infer", "infer", "detect objects and estimate 6-DoF poses in images (JSON lines + overlays)"),
    ("synth", "synth", "generate domain-randomized synthetic frames (DOPE format)"),
    ("evaluate", "evaluate", "evaluate pose predictions: HOPE tables, curves, BOP19 AR"),
    ("adapt", "adapt", "teach a model the lab's domain from unlabelled RGB-D recordings, with depth as the teacher"),
    ("calibrate", "calibrate", "choose each object's score threshold on labelled frames and record it with the weights"),
    ("export", "export", "export a checkpoint to ONNX (native or Isaac ROS layout, fp32 or INT8)"),
    ("demo", "demo", "run the shipped demo model on freshly rendered scenes (PyTorch + ONNX, -LS, errors)"),
    ("import-official", "import_official", "import NVIDIA's published DOPE weights (.pth) as checkpoints"),
    ("bop-submit", "bop_submit", "run models on a BOP test split and write a BOP19 submission CSV"),
    ("ros2", "ros2", "run as a live ROS 2 node: camera images in, poses out (pip install \"dope-hope[ros2]\")"),
    ("settings", "settings", "print a command's effective settings (defaults, --config, --set) as YAML"),
)


#: OSError numbers that mean the machine cannot do what was asked (not a bug): one line, exit 2.
ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
                      errno.ENAMETOOLONG, errno.EISDIR, errno.ENOTDIR, errno.EEXIST, errno.EIO,
                      errno.ENOENT, errno.ENXIO}


class Terminated(BaseException):
    """SIGTERM arrived (raised by the handler :func:`main` installs, like KeyboardInterrupt)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block): ``dope-hope infer: error: argument
    --threads: must be >= 1, got -1``."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dope-hope",
        description="DOPE-style 6-DoF pose estimation for the HOPE objects.")
    parser.add_argument("--version", action="version", version=f"dope-hope {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name, help_text in COMMANDS:
        module = importlib.import_module(f"dope_hope.commands.{module_name}")
        p = sub.add_parser(name, help=help_text, description=(module.__doc__ or help_text).strip())
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    prefix = f"dope-hope {args.command}"
    forget_created_folders()
    try:
        with _one_line_warnings(prefix), _sigterm_raises():
            return int(contextvars.copy_context().run(args._run, args) or 0)  # its settings stay its own
    except DopeHopeError as exc:
        remove_empty_created_folders()  # bad input: no empty --out folder left behind
        print(f"{prefix}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `dope-hope objects | head`
        sys.stderr.close()
        return 0
    except OSError as exc:
        if exc.errno not in ENVIRONMENT_ERRNOS:
            raise
        remove_empty_created_folders()
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{prefix}: error: {where}{(exc.strerror or str(exc)).lower()}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        remove_empty_created_folders()  # stopped before writing anything: no empty --out folder
        print(f"{prefix}: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        remove_empty_created_folders()
        print(f"{prefix}: terminated", file=sys.stderr)
        return 143


@contextlib.contextmanager
def _one_line_warnings(prefix: str) -> Iterator[None]:
    """Print each warning as ``PREFIX: warning: MESSAGE`` (no source line)."""
    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        print(f"{prefix}: warning: {text}", file=file or sys.stderr)

    previous = warnings.showwarning
    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` in the main thread, so that ``finally`` blocks and
    context managers clean up (worker pools, temporary files) as on Ctrl-C."""
    def handler(signum, frame):
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
