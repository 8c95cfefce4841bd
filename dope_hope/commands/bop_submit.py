"""Run models on a BOP test split and write a BOP19 submission CSV (METHOD_DATASET-SPLIT.csv).

Examples:
  dope-hope bop-submit --bop-root bop --dataset hope --split test --weights ketchup.pt \\
      --out dopehope-lite_hope-test.csv
  dope-hope bop-submit --bop-root bop --weights imported/*.pt --out dopels_hope-test.csv --overwrite
  dope-hope bop-submit --bop-root bop --weights shelf.pt mustard.onnx --out dopehope-shelf_hope-test.csv

Reads BOP_ROOT/DATASET/SPLIT/<scene_id>/{rgb,depth}/ and scene_camera.json (BOP layout; with
--bop-root pointing at the dataset folder itself, BOP_ROOT/SPLIT/ works too) and, when present,
BOP_ROOT/DATASET/test_targets_bop19.json: only the targeted images are processed, each with the
models of its targeted objects, decoding only those (a model's objects: the HOPE catalog's
obj_id of each class, or a class named obj_NNNNNN; a multi-object model covers all of its
objects with one forward pass; models of one object and of several mix).
Poses are refined with the depth line search (-LS) on the split's
depth images unless --no-depth; the line search uses the object's mesh from
BOP_ROOT/DATASET/models when found (or --models-dir: obj_NNNNNN.ply, or the other names of
dope_hope/io/models_dir.py; a --models-dir without the object's mesh is an error); --icp adds the depth ICP after it (all six DoF,
dope_hope/refine/icp.py). The inference settings are the "accurate" preset's (three working
sizes, ICP where there is depth and a mesh or box, the trained turns where not; --fast: one
size, the packaged defaults), --config and --set on top. Every estimate is written with its score and the image's total
time (reading + all models, seconds), t in millimetres (io/bop_csv.py). Evaluate it with
  dope-hope evaluate -p dopehope-lite_hope-test.csv -d bop/hope --format bop --models-dir bop/hope/models_eval
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.commands.argtypes import finite_float, fixed_device, positive_float, positive_int, working_side
from dope_hope.commands.settings import add_preset_arguments, add_settings_arguments, given_settings
from dope_hope.errors import ConfigError, InputFileError

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--bop-root", type=Path, required=True, metavar="DIR",
                        help="folder holding the BOP dataset folder (e.g. bop/ with bop/hope/test/...)")
    parser.add_argument("--dataset", default="hope", help="BOP dataset name (default hope)")
    parser.add_argument("--split", default="test", help="split folder (default test)")
    parser.add_argument("--weights", nargs="+", action="extend", type=Path, required=True, metavar="W",
                        help="checkpoint(s) / .onnx file(s) of one or more objects each (no object twice)")
    parser.add_argument("--out", type=Path, required=True, metavar="METHOD_DATASET-SPLIT.csv",
                        help="submission file; METHOD without underscores, e.g. dopehope-lite_hope-test.csv")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    parser.add_argument("--targets", type=Path, metavar="FILE",
                        help="test targets (default: DATASET/test_targets_bop19.json when present, "
                             "else every image with every model)")
    parser.add_argument("--models-dir", type=Path, metavar="DIR",
                        help="BOP models (obj_NNNNNN.ply, mm) for the line search (default DATASET/models)")
    parser.add_argument("--no-depth", action="store_true", help="no depth line search (-LS)")
    parser.add_argument("--icp", action="store_true",
                        help="after the line search, refine the whole pose by ICP against the depth")
    parser.add_argument("--depth-calibration", type=positive_float, default=1.0, metavar="F",
                        help="multiply depth by F (default 1)")
    parser.add_argument("--height", type=working_side, metavar="H", help="network working height (default: the model's)")
    parser.add_argument("--min-score", type=finite_float,
                        help="drop estimates scoring lower (default 0: BOP ranks every estimate by its score)")
    add_settings_arguments(parser, "bop-submit")
    add_preset_arguments(parser, "default --accurate")
    parser.add_argument("--backend", choices=("auto", "torch", "onnx"), default="auto")
    parser.add_argument("--device", type=fixed_device, default="cpu", help="torch device (cpu, cuda)")
    parser.add_argument("--threads", type=positive_int, help="CPU threads for the network")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dope_hope.inference.bop_estimates import estimate_frames, load_bop_models
    from dope_hope.io.bop import TEST_TARGETS_NAME, find_split_folder, targeted_frames
    from dope_hope.io.bop_csv import parse_bop_result_filename, write_bop_csv
    from dope_hope.io.paths import output_file

    parse_bop_result_filename(args.out)  # fail before any work
    options = {"min_score": 0.0, **given_settings("bop-submit", args.config, args.overrides)}
    flags = {"height": args.height, "min_score": args.min_score, "icp": True if args.icp else None}
    options.update({k: v for k, v in flags.items() if v is not None})
    args.icp = options.get("icp") is True
    if args.icp and args.no_depth:
        raise ConfigError("--icp refines against the depth: it cannot go with --no-depth")
    output_file(args.out)
    if args.out.exists() and not args.overwrite:
        raise InputFileError(args.out, "file exists; pass --overwrite to replace it")
    split_dir = find_split_folder(args.bop_root, args.dataset, args.split)
    dataset_dir = split_dir.parent
    targets_path = args.targets
    if targets_path is None and (dataset_dir / TEST_TARGETS_NAME).is_file():
        targets_path = dataset_dir / TEST_TARGETS_NAME
    models_dir = args.models_dir if args.models_dir is not None else dataset_dir / "models"
    if args.models_dir is not None and not models_dir.is_dir():
        raise InputFileError(models_dir, "models folder not found")
    if not models_dir.is_dir():
        models_dir = None  # no DATASET/models: the line search uses each model's cuboid
    models = load_bop_models(args.weights, models_dir, args.models_dir is not None, options,
                             args.backend, args.device, args.threads, preset=args.preset or "accurate")
    frames, wanted = targeted_frames(split_dir, targets_path)
    no_model = sorted({o for objs in (wanted or {}).values() for o in objs} - set(models.predictors))
    done = estimate_frames(split_dir, frames, wanted, models, use_depth=not args.no_depth,
                           depth_calibration=args.depth_calibration, progress=not args.no_progress)
    write_bop_csv(args.out, done.estimates, overwrite=args.overwrite)
    print(f"{len(done.estimates)} estimate(s) for {done.images} image(s) of {split_dir} -> {args.out}"
          + (f" ({done.seconds / done.images:.2f} s per image)" if done.images else ""))
    if no_model:
        print(f"note: no model for targeted obj_id(s) {', '.join(map(str, no_model))}: those targets get no estimate")
    return 0
