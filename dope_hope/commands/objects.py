"""List the 28 HOPE objects: BOP id, name, category, cuboid size (mesh frame) and diameter; or,
with --mesh, each mesh's symmetries as training and evaluation resolve them (those found on
the mesh: with the candidate axes tried)."""
from __future__ import annotations

import argparse
import json

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--mesh", nargs="+", default=[], metavar="PATH",
                        help="instead of the catalog: each mesh's symmetries as train and evaluate take them "
                             "(a declaration beside it, the HOPE category, else those found on the mesh) and "
                             "their BOP fields in the mesh's unit, to keep as model_info.json beside it")
    parser.add_argument("--units", choices=("m", "cm", "mm"),
                        help="unit of the --mesh files (default: .obj cm, .ply mm)")


def _mesh_symmetries(args: argparse.Namespace) -> int:
    from dope_hope.io.models_dir import mesh_class_name
    from dope_hope.io.paths import require_file
    from dope_hope.io.symmetries import mesh_units
    from dope_hope.symmetry.resolve import resolve_symmetries

    for path in args.mesh:
        require_file(path, "mesh file")
        name = mesh_class_name(path)
        found = resolve_symmetries(name, path, units=args.units)
        if found.detected is not None:
            fields = found.detected.entry(mesh_units(path, args.units))
        else:
            fields = None if found.declaration is None else found.declaration.entry
        tried = None if found.detected is None else found.detected.axes_tried
        if args.json:
            print(json.dumps({"class": name, "mesh": str(path), "symmetries": found.describe(), "fields": fields,
                              **({"axes_tried": tried} if tried else {})}))
        else:
            print(f"{name}: {found.describe()}")
            if fields is not None:
                print(f"  {json.dumps(fields)}")
            if tried:
                print(f"  axes tried: {tried}")
    return 0


def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--units")  # named in the mesh unit hints
    from dope_hope.catalog import HOPE_OBJECTS

    if args.mesh:
        return _mesh_symmetries(args)
    if args.units is not None:
        from dope_hope.errors import ConfigError

        raise ConfigError("--units is the unit of --mesh files; give --mesh")
    if args.json:
        for o in HOPE_OBJECTS:
            print(json.dumps({"obj_id": o.obj_id, "name": o.name, "category": o.category,
                              "size_m": list(o.size), "diameter_m": o.diameter,
                              "size_source": o.size_source}))
        return 0
    header = f"{'id':>2}  {'name':<18} {'category':<9} {'size x/y/z (cm)':<22} {'diam (cm)':>9}"
    print(header)
    print("-" * len(header))
    for o in HOPE_OBJECTS:
        size = "/".join(f"{100 * v:.2f}" for v in o.size)
        note = "  (size estimated)" if o.size_source == "estimate" else ""
        print(f"{o.obj_id:>2}  {o.name:<18} {o.category:<9} {size:<22} {100 * o.diameter:>9.2f}{note}")
    return 0
