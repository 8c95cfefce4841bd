"""Evaluate pose predictions against a test set: per-object HOPE table (Markdown + CSV),
detection rate vs threshold (PNG + CSV) and, for BOP data or with --bop-ar, the BOP19
average recall (AR_VSD, AR_MSSD, AR_MSPD).

Predictions: JSON lines as printed by `dope-hope infer` (one detection per line: image,
class, score, R or quaternion_xyzw, t in metres; see dope_hope/evaluation/), a BOP19
submission CSV, or a folder of NVIDIA's DOPE inference output (inference/inference.py: one
JSON per image, location in cm, quaternion_xyzw; no scores, so equal ranks in file order) to
score the official pipeline. Several files (methods) can be compared in one run.

Meshes: --mesh, then --models-dir (one search order: dope_hope/io/models_dir.py; a --models-dir
without an evaluated object's mesh is an error), else a procedural cuboid. Symmetries:
the object's BOP models_info.json entry beside its mesh, else its declaration (--symmetries
NAME=FILE, or model_info.json beside its mesh: BOP fields symmetries_discrete /
symmetries_continuous in the mesh's unit), else the HOPE catalog's category, else those found
on its mesh (dope_hope.symmetry.detect).

Instances counted (--min-visible): by default every annotated instance, HOPE's own convention
(NVlabs Deep_Object_Pose evaluate/evaluate.py counts every object of a frame's annotation);
--min-visible bop19 (0.1) counts BOP19's targets only, those at least a tenth visible. A
detection of an instance under the floor is neither a true nor a false positive.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.commands.argtypes import parse_mesh_units

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--predictions", "-p", nargs="+", required=True, type=Path, metavar="FILE",
                        help="predictions: .jsonl from `dope-hope infer`, BOP19 .csv, or a folder of "
                             "official DOPE inference output (OUTF/<weights name>)")
    parser.add_argument("--official-frame", choices=("legacy", "cuboid"), default="legacy",
                        help="official DOPE output: legacy (default; HOPE weights and networks trained on "
                             "NViSII data: rotated into the mesh frame as NVlabs evaluate.py does) or "
                             "cuboid (its cuboid frame is the mesh frame, e.g. YCB weights on FAT data)")
    parser.add_argument("--dataset", "-d", required=True, type=Path, metavar="DIR",
                        help="test set folder (searched recursively for dope/hope frames)")
    parser.add_argument("--format", choices=("auto", "dope", "hope", "bop"), default="auto",
                        help="dataset annotation format (default: auto, the layout the folder's "
                             "annotations follow, as infer finds them)")
    parser.add_argument("--metric", default="addh", metavar="M[,M...]",
                        help="error metric(s): addh (default, HOPE paper), add, adds, meanssd, mssd; "
                             "the first one fills the table, all get curves")
    parser.add_argument("--mesh", action="append", default=[], metavar="[NAME=]PATH",
                        help="object mesh (HOPE .obj in cm / BOP .ply in mm); repeat for several objects")
    parser.add_argument("--symmetries", action="append", default=[], metavar="[NAME=]FILE",
                        help="an object's symmetry declaration, BOP models_info style (default: "
                             "model_info.json beside its mesh, else the HOPE category, else those found on "
                             "its mesh); repeat for several objects")
    parser.add_argument("--models-dir", type=Path, metavar="DIR",
                        help="folder of meshes: BOP models (obj_000001.ply + models_info.json) or "
                             "HOPE (<Name>/textured.obj, <Name>.obj); it must hold every evaluated object's mesh "
                             "not given by --mesh")
    parser.add_argument("--mesh-units", action="append", default=[], metavar="[NAME=]UNIT",
                        help="unit of the mesh files, m, cm or mm (default: .obj cm, .ply mm); NAME=UNIT "
                             "for one object's mesh (repeat; objects of mixed units)")
    parser.add_argument("--out", type=Path, default=Path("out/eval"), metavar="DIR",
                        help="output folder (default: out/eval)")
    parser.add_argument("--method", nargs="+", metavar="NAME",
                        help="method name(s), one per predictions file (default: from the file)")
    ar = parser.add_mutually_exclusive_group()
    ar.add_argument("--bop-ar", dest="bop_ar", action="store_true", default=None,
                    help="compute the BOP19 average recall (default: only for --format bop)")
    ar.add_argument("--no-bop-ar", dest="bop_ar", action="store_false",
                    help="skip the BOP19 average recall")
    parser.add_argument("--min-visible", default="hope", metavar="hope|bop19|F",
                        help="count the GT instances at least this fraction visible: hope (default, 0: every "
                             "annotated instance, as HOPE's evaluation counts them), bop19 (0.1, BOP19's "
                             "targets) or a fraction in [0, 1]")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--mesh-units")  # named in the mesh unit hints
    from dope_hope.evaluation.evaluate import EvalConfig, run_evaluation
    from dope_hope.io.paths import output_dir

    output_dir(args.out)
    cfg = EvalConfig(predictions=list(args.predictions), dataset=args.dataset, fmt=args.format,
                     metrics=[m.strip().lower() for m in args.metric.split(",") if m.strip()],
                     mesh=list(args.mesh), models_dir=args.models_dir, mesh_units=parse_mesh_units(args.mesh_units),
                     out=args.out, methods=args.method, bop_ar=args.bop_ar,
                     progress=not args.no_progress, symmetries=list(args.symmetries),
                     official_frame=args.official_frame, min_visible=args.min_visible)
    run_evaluation(cfg)
    return 0
