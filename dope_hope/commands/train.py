"""Train a DOPE network (or the lite variant) for one object or several on DOPE-format folders
and/or BOP-format datasets.

Examples:
  dope-hope train --config lite --data synth/train --object Ketchup --out runs/ketchup
  dope-hope train --config lite --data synth/train --val synth/val --object Ketchup \\
      --out runs/ketchup --time-budget 20
  dope-hope train --out runs/ketchup --resume            # continue from runs/ketchup/last.pt
  torchrun --nproc_per_node 4 train.py --config dope_dr_50 --data D --object Ketchup --out R
  dope-hope train --data synth/shelf --object Can Lemon --out runs/shelf --time-budget 60
  dope-hope train --data synth/three hope/train_pbr --object Ketchup Mustard Mayo \\
      --models-dir hope/models --out runs/three

Several objects (--object A B ...): one network with a belief/affinity group per object in
the order given (model.num_objects); each instance trains its class's group. --mesh A.obj
B.obj pairs the meshes with the objects in order (or NAME=PATH). A BOP dataset (a split
such as train_pbr / train, or one scene folder, with scene_gt.json, scene_camera.json, rgb/,
mask_visib/ and the dataset's models/models_info.json) is read like a DOPE folder: obj_id i
is the run's object obj_00000i, or the HOPE object of BOP id i, else not trained.

Writes OUT/last.pt (and every checkpoint_every epochs / checkpoint_every_steps steps),
OUT/best.pt (best validation keypoint accuracy; at the end of a run that was not stopped,
with each object's own score threshold chosen on the validation frames, which infer then
uses: train.calibrate_thresholds), OUT/metrics.csv + metrics.jsonl,
OUT/summary.json, and after each validation OUT/results.png (the curves) and
OUT/val_snapshot.png (validation frames, predicted belief maps, decoded cuboids). Ctrl-C
(exit 130) and SIGTERM (exit 143) write last.pt before exiting; --resume continues exactly.
"""
from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from dope_hope.commands.argtypes import device, nonnegative_float, nonnegative_int, positive_float, positive_int
from dope_hope.commands.settings import add_settings_arguments, command_settings, given_settings
from dope_hope.config import merge
from dope_hope.errors import ConfigError, InputFileError

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def _time_budget(text: str) -> float:
    """argparse type of --time-budget: a finite number of minutes > 0, at most a year."""
    from dope_hope.training.settings import check_time_limit

    value = positive_float(text)
    try:
        return check_time_limit(value, "value")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).replace("value ", "", 1)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    add_settings_arguments(parser, "train", config_help=(
        "training recipe: a packaged one's name (lite, dope_dr_50, dope_dr_400) or a YAML file holding "
        "what it changes from the defaults (default lite); ignored with --resume, which continues with "
        "the checkpoint's recipe; `dope-hope settings train` prints every value"))
    parser.add_argument("--data", nargs="+", type=Path, metavar="DIR",
                        help="training folder(s), DOPE format or BOP datasets (with --resume: default "
                             "the checkpoint's)")
    parser.add_argument("--object", dest="object_name", nargs="+", metavar="NAME",
                        help="object class(es) to train (case-insensitive), e.g. Ketchup, or Can Lemon "
                             "for one network of several objects; 'all': every object of --models-dir (without "
                             "it: the 28 HOPE objects) (with --resume: default the checkpoint's)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--val", nargs="+", type=Path, default=[], metavar="DIR",
                        help="validation folder(s) (default: a seeded train.val_fraction split of --data)")
    parser.add_argument("--epochs", type=positive_int, help="epochs (train.epochs)")
    parser.add_argument("--steps", type=positive_int, help="total optimizer steps; overrides --epochs (train.steps)")
    parser.add_argument("--batch-size", type=positive_int, help="batch size per process (train.batch_size)")
    parser.add_argument("--workers", type=nonnegative_int, help="DataLoader workers per process (train.workers)")
    parser.add_argument("--lr", type=nonnegative_float, help="peak learning rate (train.lr)")
    parser.add_argument("--time-budget", type=_time_budget, metavar="MIN",
                        help="the run's time budget, at most a year: stop cleanly after MIN minutes with "
                             "validation and a checkpoint (train.time_limit_min). The budget becomes a step "
                             "count after the first steps, planned again from the measured speed as the run "
                             "goes; --resume counts the time used before")
    parser.add_argument("--seed", type=nonnegative_int, help="seed of init, data order and augmentation (train.seed)")
    parser.add_argument("--resume", nargs="?", const="auto", metavar="PATH",
                        help="continue from a checkpoint (no PATH: OUT/last.pt, if it exists)")
    parser.add_argument("--init", metavar="pretrained|none|demo|PATH", dest="init_weights",
                        help="the weights a new run starts from (fresh optimizer and schedule): "
                             "'pretrained' the shipped pretrained lite start (default for --config lite: "
                             "any new run whose architecture is the shipped one's), 'none' a random "
                             "start, 'demo' the shipped demo model, or a dope-hope checkpoint PATH of "
                             "the same architecture")
    parser.add_argument("--backbone-weights", type=Path, metavar="PATH",
                        help="local torchvision VGG19 state dict to initialize the trunk (arch dope)")
    parser.add_argument("--mesh", nargs="+", metavar="PATH",
                        help="object mesh(es), one per object in --object order (or NAME=PATH): the "
                             "bounding box gives the cuboid size stored in the checkpoint (default: the "
                             "size the dataset records, e.g. a synth frame, NDDS _object_settings.json, "
                             "BOP models_info.json, else the HOPE catalog's)")
    parser.add_argument("--models-dir", type=Path, metavar="DIR",
                        help="models folder holding the objects' meshes (HOPE <Name>/textured.obj, BOP "
                             "obj_NNNNNN.ply, <Name>.obj ...), instead of --mesh")
    parser.add_argument("--units", choices=("m", "cm", "mm"), nargs="+",
                        help="mesh file units, one for all meshes or one per mesh (default: .obj cm, .ply mm)")
    parser.add_argument("--symmetries", type=Path, metavar="FILE",
                        help="the object's symmetries, BOP models_info style (default: model_info.json "
                             "beside --mesh, else the HOPE category, else those found on --mesh); used by "
                             "--set targets.symmetry=auto")
    parser.add_argument("--device", type=device, default="auto", help="auto (CUDA if available), cpu, cuda")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--units")  # named in the mesh unit hints
    started = time.monotonic()  # a time budget counts the command's own checks too
    from dope_hope.io.bop_scenes import is_bop_dataset
    from dope_hope.io.dope_json import list_dope_frames
    from dope_hope.io.paths import output_dir

    if args.resume not in (None, "auto") and args.init_weights is not None:  # before any folder is made
        from dope_hope.training.settings import resolve_resume

        resolve_resume(args.resume, args.out, args.init_weights)
    output_dir(args.out)
    for folder in [*(args.data or []), *args.val]:  # fail fast, before importing torch
        if not folder.is_dir():
            raise InputFileError(folder, "data folder not found")
        if not list_dope_frames(folder) and not is_bop_dataset(folder):
            raise InputFileError(folder, "no DOPE frames (NNNNNN.json beside an image) and no BOP scenes "
                                         "(scene_gt.json + scene_camera.json) in this folder")
    from dope_hope.training.settings import TrainJob, resolve_init, resolve_resume, with_train_values
    from dope_hope.training.trainer import train

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    resume, args.init_weights = resolve_resume(args.resume, args.out, args.init_weights)

    # a new run's recipe: --config, --set and the flags over the defaults, checked once; a resumed
    # run's is its checkpoint's, with what --set and the flags give now over it (the trainer's)
    flags = {"epochs": args.epochs, "steps": args.steps, "batch_size": args.batch_size, "workers": args.workers,
             "lr": args.lr, "time_limit_min": args.time_budget, "seed": args.seed}
    flags = {key: value for key, value in flags.items() if value is not None}
    recipe, overrides = None, {}
    if resume is None:
        recipe = with_train_values(command_settings("train", args.config, list(args.overrides)), **flags)
    else:
        overrides = merge(given_settings("train", None, list(args.overrides)), {"train": flags} if flags else {})

    if resume is None and not args.data:
        raise ConfigError("--data DIR is required (the training folders)")
    if resume is None and not args.object_name:
        raise ConfigError("--object NAME is required (the class to train)")
    init_weights, why = None, ""
    if recipe is not None:
        init_weights, why = resolve_init(args.init_weights, recipe)
    from dope_hope.catalog import object_names
    from dope_hope.io.models_dir import objects_in_folder
    from dope_hope.training.settings import train_meshes

    every = args.models_dir is not None and any(n.lower() == "all" for n in args.object_name or [])
    objects = object_names(args.object_name, all_objects=objects_in_folder(args.models_dir) if every else None) \
        if args.object_name else []
    meshes, units = train_meshes(objects, args.mesh, args.models_dir, args.units)
    one = len(objects) <= 1
    job = TrainJob(data=list(args.data or []), object_name=objects[0] if objects else "", out=args.out,
                   val=list(args.val), resume=resume, mesh=next(iter(meshes.values()), None) if one else None,
                   symmetries=args.symmetries, backbone_weights=args.backbone_weights,
                   init_weights=init_weights, init_reason=why, device=args.device,
                   progress=not args.no_progress, overrides=overrides, started=started,
                   objects=[] if one else objects, meshes={} if one else meshes,
                   units={"": u for u in units.values()} if one else units,
                   mesh_name=next(iter(meshes), "") or None if not objects else None)
    summary = train(job, recipe)
    status = summary["status"]
    acc, acc_d = summary.get("val_kp_acc"), summary.get("val_kp_acc_decoded")
    acc_text = (f", val keypoints within {summary.get('val_radius_px', 5):g} px: {acc:.3f} (belief peaks), "
                f"{acc_d:.3f} (decoded instances)") if isinstance(acc, float) and isinstance(acc_d, float) else ""
    chosen = summary.get("min_scores")
    chosen_text = ("; each object's own score threshold, chosen on the validation frames, recorded in "
                   f"{summary['min_scores_file']}: " + ", ".join(f"{n} {s:g}" for n, s in chosen.items())) if chosen else ""
    if summary.get("rank", 0) == 0:
        print(f"{status}: step {summary['step']} epoch {summary['epoch']}{acc_text}; checkpoint {summary['last']}"
              f"{chosen_text}")
    return {"interrupted": 130, "terminated": 143}.get(status, 0)  # 128 + SIGINT / SIGTERM, as a shell reports
