"""See dope-hope estimate 6-DoF poses: the shipped demo model on freshly rendered scenes.

Renders --scenes random 640x480 scenes of the embedded demo box (dope_hope/demo_object.py:
one box at 0.45-0.9 m among a few distractors, RealSense-like depth noise; configs/demo.yaml;
a scene whose box is less than half visible is drawn again, dope_hope/demo/scenes.py),
runs the model through PyTorch and through onnxruntime (exported once to OUT/<weights>.onnx
and reused while the weights are unchanged), refines the distance with the depth line search
(-LS), and prints each detection next to the ground truth: translation and rotation error,
ADD-H and MeanSSD without -LS, with -LS and with -LS + ICP (dope_hope/refine/icp.py: the whole
pose refined against the depth), and how closely the ONNX keypoints agree with PyTorch's.
Detections scoring under the model's min score (its own threshold when its file records one,
as the shipped model does, else dope_hope/configs/infer.yaml's; as `dope-hope infer`) are
dropped. Ends with "found N/10 scenes with ADD-H < 2 cm (with -LS; ...)" (a scene whose box
stayed less than half visible in every draw would be left out of the count, and said so).

The errors and the matching are `dope-hope evaluate`'s (dope_hope/evaluation/matching.py), on
the model evaluate loads from OUT/mesh (500 points of DemoBox.obj, the box's symmetries from
the model_info.json written beside it), so "found N" with -LS is the true-positive count that
`dope-hope evaluate` reports for OUT/predictions.jsonl at 2 cm ADD-H (recall N/10).

Writes OUT/NNNNNN.overlay.png (detection in colour, ground truth in white), OUT/overview.png,
OUT/predictions.jsonl (PyTorch + -LS, the `dope-hope infer` format), OUT/mesh/DemoBox.obj and
OUT/mesh/model_info.json (its symmetries, BOP models_info fields) and
OUT/frames/NNNNNN.{png,depth.png,seg.png,json} (DOPE format), so that
  dope-hope infer OUT/frames/000000.png --depth auto
  dope-hope evaluate -p OUT/predictions.jsonl -d OUT/frames --mesh OUT/mesh/DemoBox.obj
work on them. Exit status 0 whatever the accuracy; 2 when it cannot run (e.g. no weights).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.commands.argtypes import positive_int
from dope_hope.commands.settings import add_settings_arguments, given_settings
from dope_hope.errors import ModelFileError

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--scenes", type=positive_int, default=10, metavar="N", help="scenes to render (default 10)")
    parser.add_argument("--seed", type=int, metavar="S",
                        help="scene seed (default: a fresh random seed, printed so the run can be repeated)")
    parser.add_argument("--out", type=Path, default=Path("demo_out"), metavar="DIR",
                        help="output folder (default ./demo_out)")
    parser.add_argument("--weights", type=Path, metavar="PATH",
                        help="demo checkpoint (default: the shipped dope_hope/assets/demo_lite.pt)")
    parser.add_argument("--no-onnx", action="store_true", help="PyTorch only (no ONNX export and run)")
    parser.add_argument("--threads", type=positive_int, metavar="T", help="CPU threads of each backend")
    add_settings_arguments(parser, "demo")


def run(args: argparse.Namespace) -> int:
    from dope_hope.demo.report import missing_weights_problem
    from dope_hope.demo.run import DemoSettings, run_demo
    from dope_hope.demo_object import write_demo_object
    from dope_hope.io.paths import output_dir

    options = given_settings("demo", args.config, args.overrides)  # checked before any work
    out = output_dir(args.out)
    if args.weights is None and not DEMO_WEIGHTS.is_file():
        # the mesh is written on purpose: the message tells how to train a demo model on it
        raise ModelFileError(DEMO_WEIGHTS, missing_weights_problem(write_demo_object(out / "mesh")))
    settings = DemoSettings(weights=args.weights if args.weights is not None else DEMO_WEIGHTS, out=out,
                            scenes=args.scenes, seed=args.seed, onnx=not args.no_onnx, threads=args.threads,
                            options=options)
    run_demo(settings, lambda text: print(text, flush=True))
    return 0
