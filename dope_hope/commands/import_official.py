"""Import NVIDIA's published DOPE weights (.pth state dicts) as dope-hope checkpoints.

Examples:
  dope-hope import-official Ketchup.pth                         # -> Ketchup.pt beside it
  dope-hope import-official weights/*.pth --out imported/       # all 28 HOPE objects at once
  dope-hope import-official dope_ketchup.pth --object Ketchup --mesh hope/meshes/Ketchup/textured.obj

The official HOPE networks are DOPE-DR-50 (VGG19 trunk, six stages), trained in the older
"legacy" keypoint frame with ImageNet normalization; the checkpoint records that, so that
`dope-hope infer`, `export` and `bop-submit` return mesh-frame poses like every other model.
The object comes from --object or the file name (a HOPE name: Ketchup.pth); its cuboid from
--mesh (the mesh's bounding box) or the catalog.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("pth", nargs="+", type=Path, metavar="PTH", help="official DOPE weights file(s)")
    parser.add_argument("--object", dest="object_name", metavar="NAME",
                        help="HOPE object of the weights (default: from the file name; one file only)")
    parser.add_argument("--out", type=Path, metavar="PATH",
                        help="output .pt (one input) or folder (default: beside each input, suffix .pt)")
    parser.add_argument("--mesh", type=Path, metavar="PATH",
                        help="object mesh: its bounding box gives the cuboid size (one file only)")
    parser.add_argument("--mesh-units", choices=("m", "cm", "mm"), help="mesh units (default: OBJ cm, PLY mm)")


def _output_path(pth: Path, out: Path | None, several: bool) -> Path:
    if out is None:
        return pth.with_suffix(".pt")
    if several or out.is_dir() or out.suffix == "":
        return out / f"{pth.stem}.pt"
    return out


def run(args: argparse.Namespace) -> int:
    from dope_hope.catalog import get_object
    from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
    from dope_hope.model.checkpoint import import_official

    several = len(args.pth) > 1
    if several and (args.object_name or args.mesh):
        raise ConfigError("--object and --mesh apply to a single weights file")
    size_m, size_source = None, "catalog"
    if args.mesh is not None:
        from dope_hope.io.meshes import load_mesh, mesh_cuboid

        size_m, _ = mesh_cuboid(load_mesh(args.mesh, units=args.mesh_units))
        size_source = f"mesh {args.mesh.name}"
    jobs = []
    for pth in args.pth:  # check every input before writing anything
        if not pth.is_file():
            raise InputFileError(pth, "weights file not found")
        name = args.object_name or pth.stem
        try:
            obj = get_object(name)
        except UnknownObjectError:
            if args.object_name:
                raise
            raise InputFileError(pth, f"cannot tell the object from the file name {pth.stem!r}; "
                                      "give --object NAME (a HOPE object, e.g. Ketchup)") from None
        out = _output_path(pth, args.out, several)
        if out.resolve() == pth.resolve():
            raise ConfigError(f"{pth}: the output would overwrite the input; give --out")
        jobs.append((pth, obj, out))
    for pth, obj, out in jobs:
        out.parent.mkdir(parents=True, exist_ok=True)
        ckpt = import_official(pth, obj.name, out_path=out, size_m=size_m)
        size_cm = " x ".join(f"{100 * v:.2f}" for v in ckpt["object"]["size_m"])
        print(f"wrote {out}: official DOPE-DR-50 weights for {obj.name} (legacy keypoint frame, "
              f"mesh-frame poses out), cuboid {size_cm} cm ({size_source})")
    return 0
