"""The default ``--min-score``: pose scores of true and false detections on held-out demo scenes.

Renders fresh scenes of `dope-hope demo` (configs/demo.yaml, 640x480, RealSense-like depth
noise; seed 3000 by default, never used for training: the shipped model trained on seeds 1
(train) and 2 (validation), the demo figures use seeds 0-9, 100, 200), runs one demo model
with ``min_score=0`` and -LS, and labels each detection: the detections are matched to the
box greedily by score (nearest centre, as the demo does); a matched detection within
:data:`TRUE_CM` ADD-H (the HOPE paper's coarse threshold) is **true** (the box, its pose
maybe a little off), every other detection (a second detection beside the box, a wrong
box-shaped set of corners) is **false**. Prints every score, the highest false and lowest true score,
and for candidate thresholds how many of each survive.

    python bench/min_score.py [--weights dope_hope/assets/demo_lite.pt] [--seeds 3000:30]
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.evaluation.matching import TABLE_THRESHOLDS_M, match_frame
from dope_hope.evaluation.object_models import load_models
from dope_hope.inference.backends import model_min_score, open_backend
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.predictor import DopePredictor

#: ADD-H (cm) under which a detection matched to the box counts as a true detection.
TRUE_CM = 10.0


@dataclass
class DemoSceneScores:
    """Pose scores of a model's detections on demo scenes, sorted ascending."""

    true: np.ndarray    # (T,) detections of the box within TRUE_CM ADD-H with -LS
    false: np.ndarray   # (F,) every other detection
    scenes: int
    boxes: int
    within_2cm: int     # true detections within the 2 cm table threshold


def demo_scene_scores(pred: DopePredictor, seeds: list[str], mesh_path: Path,
                      verbose: bool = True) -> DemoSceneScores:
    """Run ``pred`` (min score 0, the demo mesh) with -LS on the demo scenes of ``seeds``
    ("SEED:SCENES") and label each detection true or false (module docstring); ``mesh_path``:
    the demo box as :func:`~dope_hope.demo_object.write_demo_object` wrote it."""
    from dope_hope.synth import FrameGenerator

    # The demo box's model as `dope-hope evaluate` loads it (points, declared symmetries).
    model = load_models([DEMO_CLASS_NAME], [f"{DEMO_CLASS_NAME}={mesh_path}"])[DEMO_CLASS_NAME]
    threshold_cm = 100 * TABLE_THRESHOLDS_M[0]
    true, false, scenes, boxes, within_2cm = [], [], 0, 0, 0
    for item in seeds:
        seed, _, n = item.partition(":")
        with FrameGenerator(mesh_path, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME,
                            depth_noise=True, seed=int(seed)) as gen:
            for i in range(int(n or 30)):
                frame = gen.render_frame(i)
                gts = frame.annotation.objects
                dets = pred.predict(frame.rgb, frame.annotation.K, depth=frame.depth)
                match = match_frame(dets, gts, model)  # ADD-H, evaluate's one-to-one matching
                addh = {id(dets[p]): 100 * match.errors[p, g]
                        for g, p in enumerate(match.estimate_of_gt) if p >= 0}
                for d in dets:
                    (true if addh.get(id(d), np.inf) < TRUE_CM else false).append(d.score)
                    within_2cm += addh.get(id(d), np.inf) < threshold_cm
                scenes += 1
                boxes += len(gts)
                if verbose:
                    print(f"seed {seed} scene {i:3d}: " + (", ".join(
                        f"score {d.score:.3f} " + (f"ADD-H {addh[id(d)]:.2f} cm" if id(d) in addh else "unmatched")
                        + ("" if addh.get(id(d), np.inf) < TRUE_CM else " FALSE") for d in dets) or "no detection"),
                          flush=True)
    return DemoSceneScores(np.sort(true), np.sort(false), scenes, boxes, within_2cm)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    ap.add_argument("--seeds", nargs="+", default=["3000:30"], metavar="SEED:SCENES")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mesh-dir", type=Path, default=Path("runs/demo_mesh"))
    ap.add_argument("--thresholds", type=float, nargs="+",
                    default=[0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55,
                             InferenceOptions.from_mapping().min_score])
    args = ap.parse_args()

    # The network backend before any rendering: torch imported after the GL context crashes here.
    pred = DopePredictor(open_backend(args.weights, "torch", threads=args.threads), mesh=demo_object_mesh(),
                         min_score=0.0)
    s = demo_scene_scores(pred, args.seeds, write_demo_object(args.mesh_dir))
    true, false, threshold_cm = s.true, s.false, 100 * TABLE_THRESHOLDS_M[0]
    print(f"\n{args.weights}, {s.scenes} scenes ({', '.join(args.seeds)}), {s.boxes} boxes: "
          f"{len(true)} true detections (within {TRUE_CM:g} cm ADD-H with -LS; {s.within_2cm} within "
          f"{threshold_cm:g} cm), {len(false)} false")
    print(f"true scores:  min {true.min() if len(true) else float('nan'):.3f}, "
          f"lowest five {np.round(true[:5], 3).tolist()}")
    print(f"false scores: max {false.max() if len(false) else float('nan'):.3f}, all {np.round(false, 3).tolist()}")
    print("| --min-score | true kept | false kept |\n|---|---|---|")
    own = model_min_score(pred.backend)  # the model's own threshold, when its file records one
    for t in sorted(set(args.thresholds) | ({own} if own is not None else set())):
        print(f"| {t:g} | {int(np.sum(true >= t))}/{len(true)} | {int(np.sum(false >= t))}/{len(false)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
