"""The inference presets side by side on one model and one set of held-out frames: the fast
preset (the packaged defaults: one working size, -LS with depth) and the accurate one (what
`dope-hope infer` runs on still images by default: three working sizes, ICP where there is
depth and a mesh, the trained turns where not), plus any ``--candidate``, in one process on the
same CPU.

Each frame is run by every method in turn before the next frame (a shared machine's load
falls on all of them alike); a method's cost is the wall time of
:func:`dope_hope.inference.image_inference.predict_image` (reading the image and its depth,
the network at each size, decoding, the depth stages), after one warm-up frame per method.
Accuracy: `dope-hope evaluate`'s recall at 2 and 10 cm MeanSSD (:func:`run_evaluation`) over
every annotated instance (HOPE's convention) and over BOP19's targets (visible >= 0.1), and
the instances with no detection at the model's own threshold (the loss classes of
``bench/e2e_accuracy.py``), by visible fraction.

    python bench/infer_presets.py --test runs/e2e/test --weights runs/e2e/run/best.pt --count 60 \\
        --out /tmp/presets
    python bench/infer_presets.py --test runs/e2e/test --weights runs/e2e/run/best.pt \\
        --candidate 'gated=accurate:multiscale.gate=0.2' --candidate 'icp=icp=true' --out /tmp/presets_more

The mesh defaults to the shared HOPE Ketchup mesh (as ``bench/e2e_accuracy.py``). Prints the CPU,
one table (methods, seconds per frame, the ratio to the fast preset, recall, no detection) and
the loss breakdowns; writes OUT/results.md and OUT/results.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from e2e_accuracy import (  # noqa: E402
    bop_targets,
    default_mesh,
    instance_losses,
    loss_counts,
    losses_by_visibility,
    percent_text,
    recorded_threshold,
    visibility_text,
)

from dope_hope.config import merge, parse_assignment  # noqa: E402
from dope_hope.devices import cpu_line  # noqa: E402
from dope_hope.evaluation.evaluate import EvalConfig, run_evaluation  # noqa: E402
from dope_hope.inference.image_inference import ImageOptions, predict_image  # noqa: E402
from dope_hope.inference.model_set import build_predictors  # noqa: E402
from dope_hope.io.images import collect_images  # noqa: E402
from dope_hope.io.predictions import write_predictions_jsonl  # noqa: E402

#: The methods always run: name -> (preset, --set items).
BASE_METHODS = {"fast": ("fast", ()), "accurate": ("accurate", ())}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--test", type=Path, required=True, help="held-out DOPE frames with depth (e2e_accuracy's test/)")
    p.add_argument("--weights", type=Path, required=True, help="the model (a checkpoint or .onnx)")
    p.add_argument("--mesh", type=Path, help="the object's mesh (default: the shared HOPE Ketchup textured.obj)")
    p.add_argument("--object", default="Ketchup", help="its class (default Ketchup)")
    p.add_argument("--count", type=int, help="the first N frames (default all)")
    p.add_argument("--candidate", action="append", default=[], metavar="NAME=[PRESET:]KEY=VALUE[;KEY=VALUE]",
                   help="another method: a preset (fast, or accurate: ...) with these settings (--set items, ';' "
                        "between)")
    p.add_argument("--no-depth", action="store_true", help="run without the frames' depth")
    p.add_argument("--out", type=Path, required=True, help="work folder")
    args = p.parse_args(argv)
    args.mesh = default_mesh(p, args.mesh)
    return args


def methods_of(args: argparse.Namespace) -> dict[str, tuple[str, dict]]:
    """name -> (preset, the options it sets) of every method."""
    out = {name: (preset, {}) for name, (preset, _) in BASE_METHODS.items()}
    for item in args.candidate:
        name, sep, sets = item.partition("=")
        preset, colon, rest = sets.partition(":")
        preset, sets = (preset, rest) if colon and preset in BASE_METHODS else ("fast", sets)
        if not sep or not name or name in out:
            raise SystemExit(f"--candidate {item!r}: expected NAME=[PRESET:]KEY=VALUE[;KEY=VALUE] with a new NAME")
        given: dict = {}
        for assignment in filter(None, sets.split(";")):
            given = merge(given, parse_assignment(assignment))
        out[name] = (preset, given)
    return out


def subset_folder(test: Path, frames: list[Path], folder: Path) -> Path:
    """``folder`` holding links to the files of ``frames`` (each frame's image, annotation and
    depth: the files of ``test`` whose name starts with the frame's stem and a dot): the
    dataset `evaluate` scores the methods on."""
    folder.mkdir(parents=True, exist_ok=True)
    for frame in frames:
        for f in test.glob(f"{frame.stem}.*"):
            link = folder / f.name
            if not link.exists():
                link.symlink_to(f.resolve())
    return folder


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    images = collect_images([str(args.test)])[: args.count]
    methods = methods_of(args)
    predictors = {name: build_predictors([args.weights], [f"{args.object}={args.mesh}"], preset=preset, options=given)
                  for name, (preset, given) in methods.items()}
    options = ImageOptions(depth=None if args.no_depth else "auto", overlay=False)
    print(cpu_line(), flush=True)
    print(f"{len(images)} frames of {args.test}; model {args.weights}; methods {', '.join(methods)}", flush=True)
    records: dict[str, list[dict]] = {name: [] for name in methods}
    seconds = dict.fromkeys(methods, 0.0)
    for name in methods:  # warm-up: first-call costs (GL contexts, allocations) counted for none
        predict_image(predictors[name], *images[0], None, options, out)
    for k, (path, image_name) in enumerate(images):
        for name in methods:
            t0 = time.perf_counter()
            recs, _ = predict_image(predictors[name], path, image_name, None, options, out)
            seconds[name] += time.perf_counter() - t0
            records[name] += recs
        if (k + 1) % 10 == 0:
            print(f"  {k + 1}/{len(images)} frames: " + ", ".join(f"{n} {s / (k + 1):.3f} s" for n, s in seconds.items()),
                  flush=True)
    files = []
    for name in methods:
        files.append(out / f"{name.replace(' ', '_')}.jsonl")
        write_predictions_jsonl(files[-1], records[name], method=name)
    subset = subset_folder(args.test, [path for path, _ in images], out / "frames")
    recall = {}
    for floor in ("hope", "bop19"):
        summary = run_evaluation(EvalConfig(predictions=files, dataset=subset, metrics=["meanssd"],
                                            mesh=[f"{args.object}={args.mesh}"], out=out / f"eval_{floor}",
                                            methods=list(methods), bop_ar=False, min_visible=floor), log=lambda m: None)
        recall[floor] = {name: summary["methods"][name]["overall"] or {} for name in methods}
    min_score = recorded_threshold(args.weights, args.object)
    rows = ["| method | s per frame | ratio to fast | 2 cm MeanSSD | 10 cm | 2 cm, BOP targets | 10 cm, BOP targets "
            "| no detection (BOP targets) |", "|---|---|---|---|---|---|---|---|"]
    data, breakdowns = {}, []
    for name, file in zip(methods, files):
        losses = instance_losses(subset, file, args.object, args.mesh, min_score)
        lost, lost_bop = loss_counts(losses), loss_counts(bop_targets(losses))
        per_frame = seconds[name] / len(images)
        h, b = recall["hope"][name], recall["bop19"][name]
        data[name] = {"seconds_per_frame": per_frame, "ratio": seconds[name] / seconds["fast"],
                      "recall_2cm": h.get("recall_2cm"), "recall_10cm": h.get("recall_10cm"),
                      "recall_2cm_bop": b.get("recall_2cm"), "recall_10cm_bop": b.get("recall_10cm"),
                      "lost": lost, "lost_bop_targets": lost_bop, "lost_by_visibility": losses_by_visibility(losses)}
        rows.append(f"| {name} | {per_frame:.3f} | {data[name]['ratio']:.2f}x | {percent_text(h.get('recall_2cm'))} | "
                    f"{percent_text(h.get('recall_10cm'))} | {percent_text(b.get('recall_2cm'))} | "
                    f"{percent_text(b.get('recall_10cm'))} | {lost['no detection']} of {sum(lost.values())} "
                    f"({lost_bop['no detection']} of {sum(lost_bop.values())}) |")
        breakdowns.append(f"{name}, by visible fraction (scores >= {min_score:g}):\n"
                          + visibility_text(data[name]["lost_by_visibility"]))
    text = (f"# Inference presets: {len(images)} frames of {args.test}\n\n{cpu_line()}; model {args.weights}; "
            f"depth {'no' if args.no_depth else 'yes'}\n\n" + "\n".join(rows) + "\n\n" + "\n".join(breakdowns) + "\n")
    (out / "results.md").write_text(text)
    (out / "results.json").write_text(json.dumps({"frames": len(images), "weights": str(args.weights),
                                                  "methods": {n: [p, g] for n, (p, g) in methods.items()},
                                                  "cpu": cpu_line(), "results": data}, indent=1, default=float) + "\n")
    print("\n" + text + f"written: {out / 'results.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
