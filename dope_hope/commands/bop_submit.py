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
BOP_ROOT/DATASET/models (or --models-dir: obj_NNNNNN.ply, or the other names of
dope_hope/io/models_dir.py) when found; --icp adds the depth ICP after it (all six DoF,
dope_hope/refine/icp.py). Every estimate is written with its score and the image's total
time (reading + all models, seconds), t in millimetres (io/bop_csv.py). Evaluate it with
  dope-hope evaluate -p dopehope-lite_hope-test.csv -d bop/hope --format bop --models-dir bop/hope/models_eval
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.commands.argtypes import finite_float, fixed_device, positive_float, positive_int, working_side


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
    parser.add_argument("--min-score", type=finite_float, default=0.0, help="drop estimates scoring lower")
    parser.add_argument("--backend", choices=("auto", "torch", "onnx"), default="auto")
    parser.add_argument("--device", type=fixed_device, default="cpu", help="torch device (cpu, cuda)")
    parser.add_argument("--threads", type=positive_int, help="CPU threads for the network")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def obj_id_of(class_name: str) -> int:
    """BOP obj_id of a model's class (:func:`dope_hope.io.models_dir.bop_obj_id`); an error when
    it has none."""
    from dope_hope.errors import UnknownObjectError
    from dope_hope.io.models_dir import bop_obj_id

    obj_id = bop_obj_id(class_name)
    if obj_id is None:
        raise UnknownObjectError(f"model class {class_name!r} has no BOP obj_id (not a HOPE object, "
                                 "not named obj_NNNNNN)")
    return obj_id


def split_folder(bop_root: Path, dataset: str, split: str) -> Path:
    """BOP_ROOT/DATASET/SPLIT, or BOP_ROOT/SPLIT when BOP_ROOT is the dataset folder."""
    from dope_hope.errors import InputFileError

    for candidate in (bop_root / dataset / split, bop_root / split):
        if candidate.is_dir():
            return candidate
    raise InputFileError(bop_root / dataset / split, "BOP split folder not found")


def run(args: argparse.Namespace) -> int:
    import sys
    import time

    from tqdm import tqdm

    from dope_hope.errors import ConfigError, InputFileError
    from dope_hope.inference.backends import backend_objects, open_backend
    from dope_hope.inference.predictor import DopePredictor, predict_many
    from dope_hope.io.bop import iter_bop_split, list_bop_scenes, read_test_targets
    from dope_hope.io.bop_csv import (
        BopEstimate,
        parse_bop_result_filename,
        write_bop_csv,
    )
    from dope_hope.io.images import read_depth_m, read_rgb
    from dope_hope.io.models_dir import find_object_mesh
    from dope_hope.io.paths import output_file

    parse_bop_result_filename(args.out)  # fail before any work
    if args.icp and args.no_depth:
        raise ConfigError("--icp refines against the depth: it cannot go with --no-depth")
    output_file(args.out)
    if args.out.exists() and not args.overwrite:
        raise InputFileError(args.out, "file exists; pass --overwrite to replace it")
    split_dir = split_folder(args.bop_root, args.dataset, args.split)
    dataset_dir = split_dir.parent
    targets_path = args.targets
    if targets_path is None and (dataset_dir / "test_targets_bop19.json").is_file():
        targets_path = dataset_dir / "test_targets_bop19.json"
    models_dir = args.models_dir if args.models_dir is not None else dataset_dir / "models"
    if args.models_dir is not None and not models_dir.is_dir():
        raise InputFileError(models_dir, "models folder not found")
    if not models_dir.is_dir():
        models_dir = None  # no DATASET/models: the line search uses each model's cuboid

    predictors: dict[int, object] = {}  # obj_id -> the predictor of the model detecting it
    class_of: dict[int, str] = {}
    for w in args.weights:
        backend = open_backend(w, args.backend, args.device, args.threads)
        names = [o.class_name for o in backend_objects(backend)]
        ids = [obj_id_of(name) for name in names]
        for obj_id, name in zip(ids, names):
            if obj_id in predictors or ids.count(obj_id) > 1:
                raise ConfigError(f"{w}: a second model for obj_id {obj_id} ({name})")
        meshes = {name: find_object_mesh(name, models_dir, required=False) for name in names}
        pred = DopePredictor(backend, height=args.height, min_score=args.min_score, icp=args.icp,
                             mesh={k: v for k, v in meshes.items() if v is not None})
        for obj_id, name in zip(ids, names):
            predictors[obj_id], class_of[obj_id] = pred, name

    wanted: dict[tuple[int, int], list[int]] | None = None
    if targets_path is not None:
        wanted = {}
        for scene_id, im_id, obj_id, _count in read_test_targets(targets_path):
            wanted.setdefault((scene_id, im_id), []).append(obj_id)
    scene_ids = list_bop_scenes(split_dir)
    if wanted is not None:
        scene_ids = [s for s in scene_ids if any(k[0] == s for k in wanted)]
        missing = sorted({s for s, _ in wanted} - set(scene_ids))
        if missing:
            raise InputFileError(targets_path, f"targets name scene(s) {missing[:5]} that {split_dir} lacks")
    frames = [bf for bf in iter_bop_split(split_dir, scene_ids)
              if wanted is None or (bf.scene_id, bf.im_id) in wanted]
    if wanted is not None and len(frames) < len(wanted):
        found = {(bf.scene_id, bf.im_id) for bf in frames}
        s, i = sorted(set(wanted) - found)[0]
        raise InputFileError(targets_path, f"target image {i} of scene {s} is not in {split_dir}")
    no_model = sorted({o for objs in (wanted or {}).values() for o in objs} - set(predictors))

    estimates: list[BopEstimate] = []
    seconds = 0.0
    for bf in tqdm(frames, desc="bop-submit", unit="img", disable=args.no_progress, file=sys.stderr):
        frame = bf.annotation
        objs = sorted(predictors) if wanted is None else sorted(set(wanted[(bf.scene_id, bf.im_id)]) & set(predictors))
        if not objs:
            continue
        if frame.image_path is None:
            raise InputFileError(split_dir / f"{bf.scene_id:06d}", f"no image for im_id {bf.im_id}")
        t0 = time.perf_counter()
        rgb = read_rgb(frame.image_path)
        depth = None
        if not args.no_depth and frame.depth_path is not None:
            depth = read_depth_m(frame.depth_path, frame.depth_scale_m)
        models = list({id(predictors[o]): predictors[o] for o in objs}.values())
        dets = predict_many(models, rgb, frame.K, depth=depth, calibration=args.depth_calibration,
                            classes={class_of[o] for o in objs})
        elapsed = time.perf_counter() - t0
        seconds += elapsed
        by_class = {class_of[o]: o for o in objs}
        estimates += [BopEstimate(bf.scene_id, bf.im_id, by_class[d.class_name], float(d.score), d.R, d.t,
                                  round(elapsed, 4)) for d in dets]
    write_bop_csv(args.out, estimates, overwrite=args.overwrite)
    n = sum(1 for bf in frames if wanted is None or set(wanted[(bf.scene_id, bf.im_id)]) & set(predictors))
    print(f"{len(estimates)} estimate(s) for {n} image(s) of {split_dir} -> {args.out}"
          + (f" ({seconds / n:.2f} s per image)" if n else ""))
    if no_model:
        print(f"note: no model for targeted obj_id(s) {', '.join(map(str, no_model))}: those targets get no estimate")
    return 0
