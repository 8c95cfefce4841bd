"""A new object posed with no training: the pretrained start on the held-out Ketchup frames.

Runs `dope-hope infer TEST --mesh KETCHUP` without --weights (the start as a detector of the
mesh's cuboid, with the appearance check; docs/commands/infer.md "A new object with no
training") on the held-out test set of bench/e2e_accuracy.py (its ``synth-test`` stage: the
same command, seed 1001, 640x480, photo backgrounds, depth noise), with -LS (`--fast --depth
auto --min-score 0`: the still-image default would run ICP too), and with -LS + ICP (`--icp`: the depth's own fit of the mesh, where the image
alone places a bottle it never learned only roughly), and scores both with `dope-hope evaluate
--metric meanssd`: recall at 2 cm and 10 cm MeanSSD. With ``--baseline B.pt`` the same runs
for a second start and the ratios are printed (``--start`` / ``--baseline``: e.g. a newly
pretrained start against the shipped one).
Each step is a `dope-hope` command run as a subprocess (dope_hope.staged_run.CommandStages:
logged to OUT/logs/, resumable per stage). Prints the CPU and its precision flags.

    python bench/zero_training.py                                    # the shipped start, 200 frames
    python bench/zero_training.py --start new.pt --baseline dope_hope/assets/pretrained_lite.pt
    python bench/zero_training.py --test-count 3 --size 160x120 --out /tmp/zt   # plumbing only
    python bench/zero_training.py --shelf                            # six new objects in one run

``--shelf``: the six objects of bench/multi_object.py at once, none of them trained on (one
`dope-hope infer` with six ``--mesh NAME=PATH`` and each mesh's ``--up-axis``,
:data:`SHELF_UP_AXES`), on that bench's held-out scenes (its ``synth-test`` command: two to
four of the objects a frame, a photo background, depth noise): each object's recall and
their mean, beside what its 60-minute models reach (bench/RESULTS.md, "Multi-object").

Targets (the issue of this path): >= 40 % at 10 cm and >= 15 % at 2 cm with -LS (the Ketchup).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from e2e_accuracy import (  # noqa: E402
    REPO,
    SCENE,
    TEST_SEED,
    check_settings,
    percent_text,
    shared_data_dir,
    shared_defaults,
)
from multi_object import OBJECTS, TEST_SCENE, per_object_recall  # noqa: E402

from dope_hope.assets import PRETRAINED_WEIGHTS  # noqa: E402
from dope_hope.devices import cpu_line  # noqa: E402
from dope_hope.io.meshes import DEFAULT_UNITS  # noqa: E402
from dope_hope.staged_run import CommandStages  # noqa: E402

#: The targets: recall at 2 cm and 10 cm MeanSSD with -LS.
TARGETS = {"recall_2cm": 0.15, "recall_10cm": 0.40}
#: --shelf: each mesh's vertical axis (the start's y: a can's or bottle's axis). The grocery
#: meshes stand on z; the lemon's long axis, about which it turns, is x.
SHELF_UP_AXES = {"Bread": "z", "Can": "z", "Cereal": "z", "Ketchup": "y", "Lemon": "x", "Milk": "z"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--start", type=Path, default=PRETRAINED_WEIGHTS,
                   help="the start to measure (default: the shipped dope_hope/assets/pretrained_lite.pt)")
    p.add_argument("--baseline", type=Path, help="a second start, run side by side (ratios printed)")
    p.add_argument("--mesh", type=Path, help="object mesh (default: the shared HOPE Ketchup textured.obj)")
    p.add_argument("--object", default="Ketchup", help="class name (default Ketchup)")
    p.add_argument("--backgrounds", type=Path, help="test-set background photos (default: the shared ones)")
    p.add_argument("--test-count", type=int, default=200, help="held-out frames (default 200, as e2e_accuracy)")
    p.add_argument("--size", default="640x480", help="frame size WxH (default 640x480)")
    p.add_argument("--workers", type=int, default=2, help="synth render processes (default 2)")
    p.add_argument("--shelf", action="store_true",
                   help="the six objects of bench/multi_object.py in one run, on its held-out scenes")
    p.add_argument("--out", type=Path, help="work folder (default bench/out/zero_training, --shelf: ..._shelf)")
    args = p.parse_args(argv)
    args.out = args.out or REPO / "bench" / "out" / ("zero_training_shelf" if args.shelf else "zero_training")
    if args.shelf and args.mesh is not None:
        p.error("--mesh: --shelf measures the six objects of bench/multi_object.py")
    shared_defaults(p, args)
    if args.mesh.suffix.lower() not in DEFAULT_UNITS:
        p.error(f"--mesh {args.mesh}: an .obj (cm) or .ply (mm) file")
    for flag, path in (("--mesh", args.mesh), ("--start", args.start), ("--baseline", args.baseline)):
        if path is not None and not path.is_file():
            p.error(f"{flag} {path}: not a file")
    return args


def objects_of(args: argparse.Namespace) -> dict[str, tuple[Path, str, str]]:
    """{class: (mesh, unit, up axis)}: the one object (its file's default unit), or with --shelf
    the six of bench/multi_object.py."""
    if not args.shelf:
        return {args.object: (args.mesh.resolve(), DEFAULT_UNITS[args.mesh.suffix.lower()], "y")}
    shared = shared_data_dir()
    return {n: ((shared / rel).resolve(), unit, SHELF_UP_AXES[n]) for n, (rel, unit) in OBJECTS.items()}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    objects = objects_of(args)
    starts = {"start": args.start.resolve()}
    if args.baseline is not None:
        starts["baseline"] = args.baseline.resolve()
    check_settings(out, {"objects": {n: [str(m), u, a] for n, (m, u, a) in objects.items()},
                         "test_count": args.test_count, "size": args.size,
                         "starts": {k: str(v) for k, v in starts.items()},
                         "backgrounds": None if args.backgrounds is None else str(args.backgrounds.resolve())})
    print(cpu_line(), flush=True)
    pipe = CommandStages(out, cwd=REPO)
    test_dir = out / "test"
    names = list(objects)
    test = ["synth", "--mesh", *(objects[n][0] for n in names), "--units", *(objects[n][1] for n in names),
            "--no-progress", "--set", *(TEST_SCENE if args.shelf else SCENE),
            "--size", args.size, "--out", test_dir, "--count", args.test_count, "--seed", TEST_SEED,
            "--workers", args.workers, "--depth-noise"]
    if not args.shelf:
        test += ["--class-name", args.object]
    if args.backgrounds is not None:
        test += ["--backgrounds", args.backgrounds.resolve()]
    pipe.stage("synth-test", test)
    mesh_flags = [a for n, (m, u, _) in objects.items() for a in ("--mesh", f"{n}={m}", "--mesh-units", f"{n}={u}")]
    up_flags = [f"--up-axis={n}={a}" for n, (_, _, a) in objects.items()]
    for label, start in starts.items():
        # --fast: -LS alone, then --icp (the still-image default runs ICP wherever there is depth)
        infer = ["infer", test_dir, *mesh_flags, *up_flags, "--start", start, "--depth", "auto", "--min-score", "0",
                 "--fast", "--no-overlay", "--no-progress"]
        pipe.stage(f"infer-{label}", [*infer, "--out", out / label])
        pipe.stage(f"infer-{label}-icp", [*infer, "--icp", "--out", out / f"{label}_icp"])
    for suffix in ("", "_icp"):
        pipe.stage(f"eval{suffix.replace('_', '-')}", [
            "evaluate", "-p", *[out / f"{label}{suffix}" / "predictions.jsonl" for label in starts],
            "--method", *starts, "-d", test_dir, *mesh_flags, "--metric", "meanssd",
            "--no-bop-ar", "--no-progress", "--out", out / f"eval{suffix}"])
    summary = json.loads((out / "eval" / "summary.json").read_text())
    rows = {label: summary["methods"][label]["overall"] for label in starts}
    icp = json.loads((out / "eval_icp" / "summary.json").read_text())
    icp_rows = {label: icp["methods"][label]["overall"] for label in starts}
    if args.shelf:
        for label in starts:
            for suffix, tag in (("", "-LS"), ("_icp", "-LS + ICP")):
                recall = per_object_recall(out / f"eval{suffix}", label)
                print(f"{label}, {tag}, recall at 2 cm per object: "
                      + ", ".join(f"{n} {percent_text(v)}" for n, v in recall.items()))
    print(f"\n{', '.join(names)}, no training, {args.test_count} held-out frames "
          f"({summary.get('gt_instances', '?')} instances), recall at MeanSSD thresholds:")
    print("| start | weights | 2 cm, -LS | 10 cm, -LS | 2 cm, -LS + ICP | 10 cm, -LS + ICP |\n|---|---|---|---|---|---|")
    for label, start in starts.items():
        r, c = rows[label], icp_rows[label]
        print(f"| {label} | {start.name} | {percent_text(r.get('recall_2cm'))} | {percent_text(r.get('recall_10cm'))} "
              f"| {percent_text(c.get('recall_2cm'))} | {percent_text(c.get('recall_10cm'))} |")
    for key, target in ({} if args.shelf else TARGETS).items():
        value = rows["start"].get(key)
        met = value is not None and value >= target
        line = f"{key}: {percent_text(value)} (target >= {100 * target:.0f} %: {'met' if met else 'missed'})"
        if "baseline" in rows and rows["baseline"].get(key):
            line += f"; {value / rows['baseline'][key]:.2f}x the baseline's {percent_text(rows['baseline'][key])}"
        print(line)
    (out / "results.json").write_text(json.dumps({"cpu": cpu_line(), "rows": rows, "rows_icp": icp_rows,
                                                  "targets": TARGETS}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
