"""Import NVIDIA's published DOPE weights (.pth state dicts) as dope-hope checkpoints.

Examples:
  dope-hope import-official Ketchup.pth                         # -> Ketchup.pt beside it
  dope-hope import-official weights/*.pth --out imported/       # all 28 HOPE objects at once
  dope-hope import-official dope_ketchup.pth --object Ketchup --mesh hope/meshes/Ketchup/textured.obj
  dope-hope import-official net_cracker_0060.pth --dimensions 16.4036 21.3437 7.18

The official networks are DOPE-DR-50 (VGG19 trunk, six stages) with ImageNet normalization.
The object comes from --object or the file name: a HOPE name (Ketchup.pth), the official
training script's net_<name>_<epoch>.pth, or <name>_<epoch>.pth (the YCB weights).

HOPE objects: the weights use the older "legacy" keypoint frame, which the checkpoint
records so that `infer`, `export` and `bop-submit` return mesh-frame poses like every other
model; the cuboid comes from --mesh (its bounding box), --dimensions (the official config's
size, legacy frame) or the catalog. Other objects: --dimensions X Y Z in cm, as in the
official config's `dimensions`, and the poses are those of the official DOPE cuboid (its
frame, its centre), exactly what NVIDIA's inference gives; or --mesh, for weights trained on
NViSII data of that mesh (legacy frame, mesh-frame poses).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("pth", nargs="+", type=Path, metavar="PTH", help="official DOPE weights file(s)")
    parser.add_argument("--object", dest="object_name", metavar="NAME",
                        help="object of the weights (default: from the file name; one file only)")
    parser.add_argument("--out", type=Path, metavar="PATH",
                        help="output .pt (one input) or folder (default: beside each input, suffix .pt)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--mesh", type=Path, metavar="PATH",
                      help="object mesh: its bounding box gives the cuboid size (one file only)")
    size.add_argument("--dimensions", type=float, nargs=3, metavar=("X", "Y", "Z"),
                      help="cuboid size in cm as in the official DOPE config's `dimensions` (one file only)")
    parser.add_argument("--mesh-units", choices=("m", "cm", "mm"), help="mesh units (default: OBJ cm, PLY mm)")


def _output_path(pth: Path, out: Path | None, several: bool) -> Path:
    if out is None:
        return pth.with_suffix(".pt")
    if several or out.is_dir() or out.suffix == "":
        return out / f"{pth.stem}.pt"
    return out


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--mesh-units")  # named in the mesh unit hints
    import numpy as np

    from dope_hope.catalog import get_object
    from dope_hope.geometry import legacy_size_to_mesh
    from dope_hope.io.paths import output_file, require_file
    from dope_hope.model.checkpoint import import_official, official_object_name

    several = len(args.pth) > 1
    if several and (args.object_name or args.mesh or args.dimensions):
        raise ConfigError("--object, --mesh and --dimensions apply to a single weights file")
    dims_m = None
    if args.dimensions is not None:
        dims_m = 0.01 * np.asarray(args.dimensions, dtype=np.float64)
        if not np.all(np.isfinite(dims_m)) or np.any(dims_m <= 0):
            raise ConfigError(f"--dimensions: expected 3 positive sizes in cm, got {args.dimensions}")
    mesh_size, size_source = None, "catalog"
    if args.mesh is not None:
        from dope_hope.io.meshes import load_mesh, mesh_cuboid

        mesh_size, _ = mesh_cuboid(load_mesh(args.mesh, units=args.mesh_units))
        size_source = f"mesh {args.mesh.name}"
    elif dims_m is not None:
        size_source = "--dimensions"
    jobs = []
    for pth in args.pth:  # check every input before writing anything
        require_file(pth, "weights file")
        name = args.object_name or official_object_name(pth.stem)
        if name is None:
            raise InputFileError(pth, f"cannot tell the object from the file name {pth.stem!r}; "
                                      "give --object NAME")
        try:
            name = get_object(name).name
            hope = True
        except UnknownObjectError:
            hope = False
        if hope:
            # the official HOPE weights' frame; --dimensions are its (legacy-frame) sizes
            frame = "legacy"
            size_m = legacy_size_to_mesh(dims_m) if dims_m is not None else mesh_size
        elif dims_m is not None:
            frame, size_m = "mesh", dims_m  # the official cuboid frame is the object frame
        elif mesh_size is not None:
            frame, size_m = "legacy", mesh_size  # trained on NViSII data of this mesh
        else:
            cuboid = "--dimensions X Y Z (cm, as in the official DOPE config) or --mesh"
            if args.object_name:
                raise InputFileError(pth, f"{name!r} is not a HOPE object: give its cuboid as {cuboid}")
            raise InputFileError(pth, f"the file name names no HOPE object ({name!r}): give --object "
                                      f"NAME, or the cuboid as {cuboid}")
        out = _output_path(pth, args.out, several)
        if out.resolve() == pth.resolve():
            raise ConfigError(f"{pth}: the output would overwrite the input; give --out")
        output_file(out, "--out" if args.out is not None else None)
        jobs.append((pth, name, frame, size_m, out))
    for pth, name, frame, size_m, out in jobs:
        ckpt = import_official(pth, name, out_path=out, size_m=size_m, frame=frame)
        size_cm = " x ".join(f"{100 * v:.2f}" for v in ckpt["object"]["size_m"])
        poses = ("legacy keypoint frame, mesh-frame poses out" if frame == "legacy"
                 else "poses of the official DOPE cuboid")
        print(f"wrote {out}: official DOPE-DR-50 weights for {name} ({poses}), cuboid {size_cm} cm "
              f"({size_source})")
    return 0
