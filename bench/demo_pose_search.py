"""Demo scenes found: the multi-hypothesis pose search against DOPE's one corner per type.

Renders the scenes of `dope-hope demo` (configs/demo.yaml, 640x480, RealSense-like depth
noise; frame i of seed S, the frame `dope-hope demo --seed S` shows as scene i unless its box
is less than half visible, which the demo draws again and this bench keeps), runs one demo model through
both pose searches of ``DopePredictor`` on the same network maps - the default
``pose_search="hypotheses"`` (maps.decode.corner_candidates + inference.pose_search.solve_pnp_candidates)
and ``"groups"`` (maps.decode.decode_maps + inference.pnp.solve_pnp) - with -LS, and scores each
scene as the demo and `dope-hope evaluate` do (dope_hope/evaluation/matching.match_frame):
detections in descending score take the box when their ADD-H is below 2 cm, a scene is found
when its box is; detections paired with no box are false positives.

    python bench/demo_pose_search.py [--weights dope_hope/assets/demo_lite.pt] [--seeds 100:40 200:40 0:10 1:10 2:10 3:10]

Prints scenes found, false positives and decode + PnP time per scene for each search, and
their ratios.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from tqdm import tqdm

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.evaluation.matching import TABLE_THRESHOLDS_M, match_frame
from dope_hope.evaluation.object_models import load_models
from dope_hope.inference.backends import open_backend
from dope_hope.inference.predictor import DopePredictor
from dope_hope.refine.depth import DepthImage
from dope_hope.synth import FrameGenerator

SEARCHES = ("hypotheses", "groups")


def parse_seeds(items: list[str]) -> list[tuple[int, int]]:
    """["100:40", "0:10"] -> [(100, 40), (0, 10)] (seed, scenes)."""
    out = []
    for item in items:
        seed, _, n = item.partition(":")
        out.append((int(seed), int(n or 10)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    ap.add_argument("--seeds", nargs="+", default=["100:40", "200:40", "0:10", "1:10", "2:10", "3:10"],
                    metavar="SEED:SCENES")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mesh-dir", type=Path, default=Path("runs/demo_mesh"))
    args = ap.parse_args()

    mesh = demo_object_mesh()
    mesh_path = write_demo_object(args.mesh_dir)
    backend = open_backend(args.weights, "torch", threads=args.threads)
    # min_score 0: every detection counts, as in the figures of bench/RESULTS.md.
    predictors = {s: DopePredictor(backend, mesh=mesh, pose_search=s, min_score=0.0) for s in SEARCHES}
    model = load_models([DEMO_CLASS_NAME], [str(mesh_path)])[DEMO_CLASS_NAME]
    found = {s: 0 for s in SEARCHES}
    false_pos = {s: 0 for s in SEARCHES}
    seconds = {s: 0.0 for s in SEARCHES}
    per_seed: dict[str, list[str]] = {s: [] for s in SEARCHES}
    scenes = 0
    seeds = parse_seeds(args.seeds)
    with tqdm(total=sum(n for _, n in seeds), desc="demo scenes", unit="scene") as bar:
        for seed, n in seeds:
            counts = {s: 0 for s in SEARCHES}
            with FrameGenerator(mesh_path, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME,
                                depth_noise=True, seed=seed) as gen:
                for i in range(n):
                    frame = gen.render_frame(i)
                    K, gts = frame.annotation.K, frame.annotation.objects
                    belief, affinity, net_in = predictors["groups"].infer_maps(frame.rgb)
                    depth = DepthImage.from_raw(frame.depth, K, image_hw=frame.rgb.shape[:2])
                    for s, pred in predictors.items():
                        t0 = time.perf_counter()
                        dets = pred.detections_from_maps(belief, affinity, net_in, K, depth=depth)
                        seconds[s] += time.perf_counter() - t0
                        match = match_frame(dets, gts, model)
                        counts[s] += match.found
                        false_pos[s] += match.unpaired
                    scenes += 1
                    bar.update()
            for s in SEARCHES:
                found[s] += counts[s]
                per_seed[s].append(f"{seed}: {counts[s]}/{n}")

    print(f"{args.weights}: {scenes} demo scenes, ADD-H < {100 * TABLE_THRESHOLDS_M[0]:g} cm with -LS")
    for s in SEARCHES:
        print(f"  {s:10s}: found {found[s]:3d}/{scenes} ({100 * found[s] / scenes:.1f} %)  false positives "
              f"{false_pos[s]:3d}  decode + PnP + -LS {1000 * seconds[s] / scenes:6.1f} ms/scene   "
              f"[{', '.join(per_seed[s])}]")
    print(f"  hypotheses / groups: scenes found {found['hypotheses'] / max(found['groups'], 1):.2f}x, "
          f"time {seconds['hypotheses'] / max(seconds['groups'], 1e-9):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
