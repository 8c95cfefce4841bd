"""``dope-hope``: the command-line entry point.

Each subcommand lives in ``dope_hope/commands/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports (torch, pyrender) happen inside ``run`` so that
``dope-hope --help`` stays fast. A :class:`DopeHopeError` is printed on one line and the
process exits with status 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from dope_hope import __version__
from dope_hope.errors import DopeHopeError

#: (subcommand, module under dope_hope.commands, one-line help)
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("objects", "objects", "list the 28 HOPE objects"),
    ("train", "train", "train a network for one object on DOPE-format folders"),
    ("infer", "infer", "detect objects and estimate 6-DoF poses in images (JSON lines + overlays)"),
    ("synth", "synth", "generate domain-randomized synthetic frames (DOPE format)"),
    ("evaluate", "evaluate", "evaluate pose predictions: HOPE tables, curves, BOP19 AR"),
    ("export", "export", "export a checkpoint to ONNX (native or Isaac ROS layout, fp32 or INT8)"),
    ("demo", "demo", "run the shipped demo model on freshly rendered scenes (PyTorch + ONNX, -LS, errors)"),
    ("import-official", "import_official", "import NVIDIA's published DOPE weights (.pth) as checkpoints"),
    ("bop-submit", "bop_submit", "run models on a BOP test split and write a BOP19 submission CSV"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    try:
        return int(args._run(args) or 0)
    except DopeHopeError as exc:
        print(f"dope-hope {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `dope-hope objects | head`
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"dope-hope {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
