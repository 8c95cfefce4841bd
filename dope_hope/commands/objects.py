"""List the 28 HOPE objects: BOP id, name, category, cuboid size (mesh frame) and diameter."""
from __future__ import annotations

import argparse
import json

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON object per line")


def run(args: argparse.Namespace) -> int:
    from dope_hope.catalog import HOPE_OBJECTS

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
