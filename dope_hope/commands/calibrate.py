"""Choose each object's own score threshold on labelled frames and record it with the weights.

A model's pose scores are its own, and in a model of several objects each object's are: one
--min-score keeps one object's detections and drops another's. Give this command the
estimates a model made with no threshold on labelled frames that it was neither trained nor
will be benchmarked on; it matches them to the labels as `evaluate` does (--metric; an
estimate within --within-cm of an instance of its object is true), picks for each object the
threshold with the highest F1 (found instances against false detections;
dope_hope/evaluation/thresholds.py) and writes a copy of the weights (--out, without their
training state) that records them. `infer`, `demo`, DopePredictor and the weights' ONNX
export then use each object's own threshold unless --min-score / min_score is given
(`bop-submit` keeps every estimate, as the BOP19 score ranks them).

    dope-hope infer calib/ --weights run/best.pt --min-score 0 --depth auto --mesh ... --out calib_pred
    dope-hope calibrate -p calib_pred/predictions.jsonl -d calib/ --weights run/best.pt --mesh ... \\
        --out run/calibrated.pt

Meshes, units and symmetries as for `evaluate`.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.commands.argtypes import parse_mesh_units

# The library is imported inside the functions: cli.py imports every command to build --help.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--predictions", "-p", required=True, type=Path, metavar="FILE",
                        help="the model's estimates on the frames, from `dope-hope infer --min-score 0` "
                             "(.jsonl)")
    parser.add_argument("--dataset", "-d", required=True, type=Path, metavar="DIR",
                        help="the labelled frames the estimates were made on (not training or test frames)")
    parser.add_argument("--format", choices=("auto", "dope", "hope", "bop"), default="auto",
                        help="dataset annotation format (default: auto)")
    parser.add_argument("--weights", required=True, type=Path, metavar="FILE",
                        help="the checkpoint (.pt) that made the estimates")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE",
                        help="the checkpoint to write: the weights with each object's threshold (.pt)")
    parser.add_argument("--metric", default="meanssd", metavar="M",
                        help="error metric of a match: meanssd (default), mssd, addh, add, adds")
    parser.add_argument("--within-cm", type=float, default=10.0, metavar="CM",
                        help="an estimate this close to an instance of its object is true (default 10)")
    parser.add_argument("--mesh", action="append", default=[], metavar="[NAME=]PATH",
                        help="object mesh; repeat for several objects (as for evaluate)")
    parser.add_argument("--symmetries", action="append", default=[], metavar="[NAME=]FILE",
                        help="an object's symmetry declaration, BOP models_info style (as for evaluate)")
    parser.add_argument("--models-dir", type=Path, metavar="DIR", help="folder of meshes (as for evaluate)")
    parser.add_argument("--mesh-units", action="append", default=[], metavar="[NAME=]UNIT",
                        help="unit of the mesh files, m, cm or mm (default: .obj cm, .ply mm)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--mesh-units")  # named in the mesh unit hints
    from dope_hope.evaluation.thresholds import calibrate_weights, thresholds_table

    choices, before = calibrate_weights(
        args.predictions, args.dataset, args.weights, args.out, fmt=args.format, metric=args.metric.strip().lower(),
        within_m=args.within_cm / 100.0, mesh=list(args.mesh), models_dir=args.models_dir,
        mesh_units=parse_mesh_units(args.mesh_units), symmetries=list(args.symmetries),
        progress=not args.no_progress)
    print(thresholds_table(choices, before, args.within_cm))
    print(f"written: {args.out} (each object's min score; --min-score overrides them)")
    return 0
