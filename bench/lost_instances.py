"""Why each held-out instance a model does not detect is lost, by visible fraction.

For every GT instance of the object with no detection at the model's own threshold in a
predictions file (`dope-hope infer ... --min-score 0`, as ``bench/e2e_accuracy.py`` writes
them; the loss classes of that script), the first cause that applies, read on the network's
maps at the working size (:meth:`DopePredictor.infer_maps`, the fast preset's one size):

1. ``under a tenth visible``: no BOP19 target (visible < 0.1).
2. ``score below the threshold``: a detection under the threshold lies within 10 cm MeanSSD
   of it (the maps found it; the pose's score is too low to keep).
3. ``centroid not seen``: the centroid's belief within 2 map cells of its projection stays
   under the decode threshold (``decode.threshold``): the centroid-led grouping has nothing
   to group the corners around.
4. ``too few keypoints``: fewer of the nine keypoints than PnP needs (``pnp.min_points``) have
   belief above the threshold within 2 cells of their projections.
5. ``seen, not posed``: enough keypoints and the centroid seen, yet no pose within 10 cm (the
   grouping or the pose search lost it).

With ``--also PREDICTIONS`` (e.g. the three working sizes' or the accurate preset's file) each
cause also counts the instances that file detects within 10 cm at the threshold.

    python bench/lost_instances.py --test runs/e2e/test --weights runs/e2e/run/best.pt \\
        --predictions runs/e2e/infer_ls/predictions.jsonl --also runs/e2e/infer_scales/predictions.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from e2e_accuracy import (  # noqa: E402
    BOP_VISIBLE_FLOOR,
    VISIBILITY_BANDS,
    default_mesh,
    recorded_threshold,
)

from dope_hope.devices import cpu_line  # noqa: E402
from dope_hope.evaluation.datasets import assign_predictions, load_dataset  # noqa: E402
from dope_hope.evaluation.evaluate import cuboid_centres_to_origins  # noqa: E402
from dope_hope.evaluation.matching import error_matrix, match_frame  # noqa: E402
from dope_hope.evaluation.object_models import load_models  # noqa: E402
from dope_hope.geometry import project_points  # noqa: E402
from dope_hope.inference.predictor import DopePredictor  # noqa: E402
from dope_hope.io.images import read_rgb  # noqa: E402
from dope_hope.io.predictions import read_predictions  # noqa: E402

#: The causes, in the order they are tested (module docstring).
CAUSES = ("under a tenth visible", "score below the threshold", "centroid not seen", "too few keypoints",
          "seen, not posed")
#: How far from a keypoint's projection its belief counts, map cells.
SEEN_RADIUS_CELLS = 2
#: An estimate within this MeanSSD of an instance places it, metres (the table's 10 cm).
PLACED_M = 0.10


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--test", type=Path, required=True, help="held-out DOPE frames (e2e_accuracy's test/)")
    p.add_argument("--weights", type=Path, required=True, help="the model")
    p.add_argument("--predictions", type=Path, required=True, help="its predictions, every score (--min-score 0)")
    p.add_argument("--also", type=Path, action="append", default=[], help="other predictions of the same frames")
    p.add_argument("--mesh", type=Path, help="the object's mesh (default: the shared HOPE Ketchup textured.obj)")
    p.add_argument("--object", default="Ketchup", help="its class (default Ketchup)")
    p.add_argument("--out", type=Path, help="write the counts as JSON here")
    args = p.parse_args(argv)
    args.mesh = default_mesh(p, args.mesh)
    return args


def seen_keypoints(predictor: DopePredictor, belief: np.ndarray, net_in, K: np.ndarray, R: np.ndarray,
                   t: np.ndarray) -> np.ndarray:
    """(9,) bool: the instance's keypoints (pose R, t) whose belief within
    :data:`SEEN_RADIUS_CELLS` of their projection exceeds the decode threshold."""
    uv = net_in.to_network_px(project_points(predictor.cuboid_mesh, K, R, t)) / predictor.stride
    h, w = belief.shape[1:]
    r = SEEN_RADIUS_CELLS
    seen = np.zeros(len(uv), dtype=bool)
    for k, (u, v) in enumerate(uv):
        if not (np.isfinite(u) and np.isfinite(v)) or not (-r <= u < w + r and -r <= v < h + r):
            continue
        c0, c1 = max(0, int(round(u)) - r), min(w, int(round(u)) + r + 1)
        r0, r1 = max(0, int(round(v)) - r), min(h, int(round(v)) + r + 1)
        seen[k] = c0 < c1 and r0 < r1 and belief[k, r0:r1, c0:c1].max() > predictor.options.decode.threshold
    return seen


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    dataset = load_dataset(args.test)
    models = load_models([args.object], [f"{args.object}={args.mesh}"], recorded_sizes=dataset.cuboid_sizes)
    model = models[args.object]
    threshold = recorded_threshold(args.weights, args.object)
    predictor = DopePredictor(args.weights, mesh=args.mesh)
    files = [args.predictions, *args.also]
    per_frame = []
    for path in files:
        preds = [p for p in read_predictions(path)[0] if p.class_name == args.object]
        cuboid_centres_to_origins(preds, models)
        per_frame.append(assign_predictions(dataset, preds)[0])
    counts = {label: {c: 0 for c in CAUSES} for label, _, _ in VISIBILITY_BANDS}
    rescued = {label: {c: [0] * len(args.also) for c in CAUSES} for label, _, _ in VISIBILITY_BANDS}
    lost = total = 0
    for fi, frame in enumerate(dataset.frames):
        gts = [o for o in frame.objects if o.class_name == args.object]
        if not gts:
            continue
        maps = None
        ests = per_frame[0][fi]
        kept = [e for e in ests if e.score >= threshold]
        below = [e for e in ests if e.score < threshold]
        paired = match_frame(kept, gts, model, metric="meanssd").estimate_of_gt  # as e2e_accuracy pairs them
        for g, gt in enumerate(gts):
            total += 1
            if paired[g] >= 0:
                continue  # a detection at the threshold is paired with it: not lost to "no detection"
            lost += 1
            errors = error_matrix("meanssd", below, [gt], model)[:, 0] if below else np.zeros(0)
            visible = 1.0 if gt.visibility is None else float(gt.visibility)
            if visible < BOP_VISIBLE_FLOOR:
                cause = CAUSES[0]
            elif np.any(errors < PLACED_M):
                cause = CAUSES[1]
            else:
                if maps is None:
                    maps = predictor.infer_maps(read_rgb(frame.image_path))
                belief, _, net_in = maps
                seen = seen_keypoints(predictor, belief, net_in, frame.K, gt.R, gt.t)
                cause = (CAUSES[2] if not seen[8] else CAUSES[3]
                         if seen.sum() < predictor.options.pnp.min_points else CAUSES[4])
            band = next(label for label, lo, hi in VISIBILITY_BANDS if lo <= visible < hi)
            counts[band][cause] += 1
            for j in range(len(args.also)):
                others = [e for e in per_frame[j + 1][fi] if e.score >= threshold]
                if others and np.any(error_matrix("meanssd", others, [gt], model)[:, 0] < PLACED_M):
                    rescued[band][cause][j] += 1
    print(cpu_line())
    print(f"{args.predictions}: {lost} of {total} instances with no detection at the threshold {threshold:g}")
    for band, by_cause in counts.items():
        print(f"  visible {band}: " + ", ".join(
            f"{c} {n}" + (f" (placed within 10 cm by {'/'.join(str(x) for x in rescued[band][c])} of --also)"
                          if args.also and n else "") for c, n in by_cause.items()))
    if args.out is not None:
        args.out.write_text(json.dumps({"predictions": str(args.predictions), "also": [str(a) for a in args.also],
                                        "threshold": threshold, "lost": lost, "total": total,
                                        "causes": counts, "placed_by_also": rescued}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
