"""A demo model's own score threshold, chosen on photographs WITHOUT the box, and recorded.

A model's scores are its own: a longer-trained or differently trained model scores the
box-like things of real photographs differently, so one packaged ``min_score`` cannot hold
every model's false detections down. This script chooses a threshold for one demo-box model
(--weights) and, with --write, saves a copy of the weights that records it
(``ModelInfo.min_score``): `dope-hope infer`, `dope-hope demo`, ``DopePredictor`` and the
model's ONNX export then use it unless --min-score / ``min_score`` is given.

The rule: the smallest min score, from the packaged default (configs/infer.yaml) up in steps
of --step, at which --empty random crops of the calibration photographs (--photos: held out
from the model's training AND from the photographs it is benchmarked on) hold a detection in
at most --target-per-50 / --margin frames per 50 (default 1 / 2: half the false-detection
target, a margin for photographs it has never seen). The crops are bench/photo_composite.py's
empty crops (640x480, its camera). For each candidate it also prints what the threshold costs
on fresh demo scenes (bench/min_score.py's labelling: true detections of the box kept), so a
threshold that would drop the box is seen before it is recorded. Exit status 1 when no
candidate up to 0.95 meets the target (nothing written).

    python bench/model_threshold.py --weights run/best.pt --photos heldout/motorcycle_left.png \\
        [--empty 400] [--seed 7] [--seeds 3000:30 3001:30] [--write dope_hope/assets/demo_lite.pt]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from min_score import demo_scene_scores
from photo_composite import composite_config, empty_photo_scores

from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.inference.backends import open_backend
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.predictor import DopePredictor
from dope_hope.model.checkpoint import save_inference_checkpoint

#: Highest candidate threshold.
MAX_THRESHOLD = 0.95


def candidates(start: float, step: float) -> list[float]:
    """Thresholds from ``start`` up to :data:`MAX_THRESHOLD` in steps of ``step`` (rounded)."""
    n = int(math.floor((MAX_THRESHOLD - start) / step + 1e-9))
    return [round(start + k * step, 6) for k in range(n + 1)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, required=True, help="demo-box checkpoint to choose for")
    ap.add_argument("--photos", type=Path, nargs="+", required=True,
                    help="calibration photographs (folders and/or files), not the model's training "
                         "photographs nor its benchmark's")
    ap.add_argument("--empty", type=int, default=400, help="random crops without the box (default 400)")
    ap.add_argument("--seed", type=int, default=7, help="seed of the crops (default 7)")
    ap.add_argument("--seeds", nargs="+", default=["3000:30", "3001:30"], metavar="SEED:SCENES",
                    help="demo scenes for the cost on true detections (default 3000:30 3001:30)")
    ap.add_argument("--target-per-50", type=float, default=1.0,
                    help="false-detection target, frames with a detection per 50 (default 1)")
    ap.add_argument("--margin", type=float, default=2.0, help="the rule asks for target / margin (default 2)")
    ap.add_argument("--step", type=float, default=0.05, help="candidate spacing (default 0.05)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mesh-dir", type=Path, default=Path("runs/demo_mesh"))
    ap.add_argument("--write", type=Path, help="save the weights here with the chosen threshold recorded")
    args = ap.parse_args()

    start = InferenceOptions.from_mapping().min_score  # the packaged default, never below it
    grid = candidates(start, args.step)
    # The network backend before any rendering: torch imported after the GL context crashes here.
    pred = DopePredictor(open_backend(args.weights, "torch", threads=args.threads), mesh=demo_object_mesh(),
                         min_score=0.0)
    from dope_hope.synth import FrameGenerator

    mesh_path = write_demo_object(args.mesh_dir)
    with FrameGenerator(mesh_path, size=(640, 480), config=composite_config(), class_name=DEMO_CLASS_NAME,
                        backgrounds=args.photos, seed=args.seed) as gen:
        empty = empty_photo_scores(gen, pred, args.photos, args.empty, args.seed)
    demo = demo_scene_scores(pred, args.seeds, mesh_path, verbose=False)
    allowed = args.target_per_50 / args.margin
    print(f"{args.weights}: {args.empty} crops of {' '.join(map(str, args.photos))} without the box "
          f"(seed {args.seed}); {len(demo.true)} true and {len(demo.false)} false detections on "
          f"{demo.scenes} demo scenes ({' '.join(args.seeds)}); rule: at most {allowed:g} crops "
          f"with a detection per 50")
    print("\n| min score | crops with a detection | per 50 | demo: true kept | demo: false kept |")
    print("|---|---|---|---|---|")
    chosen = None
    for t in grid:
        frames = sum(any(s >= t for s in scores) for scores in empty)
        per_50 = 50.0 * frames / max(args.empty, 1)
        print(f"| {t:g} | {frames}/{args.empty} | {per_50:.2f} | {int(np.sum(demo.true >= t))}/{len(demo.true)} "
              f"| {int(np.sum(demo.false >= t))}/{len(demo.false)} |")
        if chosen is None and per_50 <= allowed:
            chosen = t
    if chosen is None:
        print(f"\nno threshold up to {MAX_THRESHOLD:g} keeps the crops at {allowed:g} per 50; nothing written")
        return 1
    print(f"\nchosen: {chosen:g}")
    if args.write is not None:
        save_inference_checkpoint(args.weights, args.write, min_score=chosen)
        print(f"written: {args.write} (min_score {chosen:g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
