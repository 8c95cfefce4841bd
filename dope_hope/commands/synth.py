"""Generate domain-randomized synthetic training frames (DOPE format) for one or several objects.

Examples:
  dope-hope synth --mesh ../shared/data/hope_ketchup/textured.obj --out synth/ketchup --count 2000
  dope-hope synth --models-dir hope/meshes/full --object Ketchup --out synth/ketchup --count 20000 \\
      --workers 2 --backgrounds coco/val2017 --distractors hope/meshes/full --preview
  dope-hope synth --models-dir bop/hope/models --object Ketchup --out D --count 100000 --shard 3/8
  dope-hope synth --procedural --out pretrain/frames --count 24000 --size 256x192 --workers 2
  dope-hope synth --mesh grocery/Can/textured.obj grocery/Lemon/textured.obj --units m \\
      --out synth/shelf --count 4000 --set target.count=[0,4]
  dope-hope synth --models-dir hope/meshes/full --object Ketchup Mustard Mayo --out synth/three --count 6000

Writes OUT/NNNNNN.png (RGB), NNNNNN.depth.png (uint16 mm, 0 = no depth), NNNNNN.seg.png
(uint8: 0 background, 1..k target instances = the JSON's instance_id, 101.. distractors),
NNNNNN.json (project DOPE format: intrinsics, class, pose, projected cuboid, visibility,
bounding box; extra keys "cuboid" and "synth") and OUT/_synth_info.json (settings).
Several target objects (--mesh A B ..., --object A B ..., --object all): each frame's
target.count instances take their objects from a random permutation of them (distinct objects
while the count allows; a count of 0 is a negative frame) and each JSON object names its class;
a mesh's class is the object its file names (HOPE name, obj_NNNNNN), else the folder of a
generic file name (Can/textured.obj -> Can), else the file stem; --class-name sets them.
--procedural renders a new box, can or bottle of HOPE size with a packaging-like texture in
every frame (class "Object", each frame's JSON records its cuboid; docs/commands/train.md, "Pretraining").
Frame i depends only on (--seed, i): reruns, --workers and --shard give identical frames.
Resumable: frames whose JSON exists are skipped (the JSON is written last).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.commands.argtypes import nonnegative_int, positive_int
from dope_hope.commands.settings import add_settings_arguments
from dope_hope.errors import ConfigError

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    src = parser.add_argument_group("target objects (one of)")
    src.add_argument("--mesh", type=Path, nargs="+", metavar="PATH",
                     help="target mesh(es): HOPE textured .obj (cm) or BOP .ply (mm); several: "
                          "several target objects per frame")
    src.add_argument("--models-dir", type=Path, metavar="DIR",
                     help="models folder (HOPE <Name>/textured.obj or BOP obj_NNNNNN.ply); with --object")
    src.add_argument("--object", dest="object_name", nargs="+", metavar="NAME",
                     help="object name(s) in --models-dir, e.g. Ketchup Mustard; 'all': every object the folder holds")
    src.add_argument("--procedural", action="store_true",
                     help="a new procedural box / can / bottle per frame (pretraining data; config "
                          "section 'procedural')")
    parser.add_argument("--units", choices=("m", "cm", "mm"), nargs="+",
                        help="mesh file units, one for all meshes or one per mesh (default: .obj cm, .ply mm)")
    parser.add_argument("--class-name", nargs="+", metavar="NAME",
                        help="class written in the JSON, one per mesh (default: the HOPE name, else the "
                             "folder of a generic file name such as textured.obj, else the file stem)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--count", type=nonnegative_int, required=True, metavar="N", help="frames 0..N-1")
    parser.add_argument("--workers", type=positive_int, default=1, metavar="W",
                        help="render processes on this machine (default 1)")
    parser.add_argument("--shard", metavar="i/n", help="only frames with index %% n == i (several machines)")
    parser.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    parser.add_argument("--size", default="640x480", metavar="WxH", help="image size (default 640x480)")
    parser.add_argument("--backgrounds", type=Path, nargs="+", metavar="PATH",
                        help="background photos (random crops): folders (searched recursively) "
                             "and/or image files; default: procedural backgrounds")
    parser.add_argument("--distractors", type=Path, metavar="DIR",
                        help="extra distractor meshes (.obj/.ply, e.g. the other HOPE objects; copies "
                             "of the target are excluded); default: procedural primitives only")
    add_settings_arguments(parser, "synth", config_help=(
        "generator ranges: a packaged config's name (synth, demo, procedural) or a YAML file, holding "
        "what it changes from dope_hope/configs/synth.yaml (default synth: those defaults)"))
    parser.add_argument("--depth-noise", action="store_true",
                        help="RealSense-like noise and holes in the written depth")
    parser.add_argument("--preview", action="store_true",
                        help="write OUT/preview.png: frames with their projected cuboids")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--units")  # named in the mesh unit hints
    from dope_hope.catalog import object_names
    from dope_hope.io.models_dir import find_object_mesh, objects_in_folder
    from dope_hope.io.paths import output_dir
    from dope_hope.synth.generate import SynthJob
    from dope_hope.synth.settings import load_synth_config
    from dope_hope.synth.to_disk import generate_dataset

    if args.mesh is not None and (args.models_dir is not None or args.object_name is not None):
        raise ConfigError("give either --mesh or --models-dir with --object, not both")
    if args.procedural and (args.mesh is not None or args.models_dir is not None or args.object_name is not None):
        raise ConfigError("--procedural makes its own objects: drop --mesh / --models-dir / --object")
    if args.procedural:
        mesh = None
    elif args.mesh is not None:
        mesh = args.mesh
    elif args.models_dir is not None and args.object_name is not None:
        names = object_names(args.object_name, all_objects=objects_in_folder(args.models_dir)
                             if any(n.lower() == "all" for n in args.object_name) else None)
        mesh = [find_object_mesh(name, args.models_dir) for name in names]
    else:
        raise ConfigError("no target: give --mesh PATH, --models-dir DIR --object NAME or --procedural")
    class_name = args.class_name or (names if args.object_name is not None else None)
    # one value stays one value: a one-object run passes the arguments it always did
    mesh, class_name, units = (v[0] if v is not None and len(v) == 1 else v
                               for v in (mesh, class_name, args.units))
    config = load_synth_config(args.config, args.overrides)
    output_dir(args.out)
    job = SynthJob(mesh, seed=args.seed, size=args.size, config=config, class_name=class_name, units=units,
                   backgrounds=args.backgrounds, distractors=args.distractors, depth_noise=args.depth_noise,
                   procedural=args.procedural)
    summary = generate_dataset(args.out, job, args.count, workers=args.workers, shard=args.shard,
                               preview=args.preview, progress=not args.no_progress)
    print(f"{summary.written} frames written, {summary.skipped} already there, "
          f"{summary.frames_per_s:.2f} frames/s -> {summary.out_dir}")
    if summary.preview is not None:
        print(f"preview: {summary.preview}")
    return 0
