"""Decoding speed: a trained model's maps -> poses, candidate and baseline side by side, and
whether the two give the same detections.

The network runs once, in this checkout: the maps of the first ``--frames`` frames of a
DOPE-format folder (held-out frames: RGB + JSON with the camera), per ``--weights`` file. Each
arm then, in its own process (``PYTHONPATH`` = its checkout), builds ``DopePredictor(weights)``
and times ``detections_from_maps`` on every frame's maps (no depth: decoding, pose search and
PnP), ``--rounds`` times, the arms alternating; per arm and model the median over rounds of the
mean milliseconds per frame, the ratio candidate / baseline, and the detections of the two arms
compared frame by frame (class, score, pose to 1e-6). Both arms use the packaged inference
defaults unless ``--min-score`` is given.

The candidate is this checkout; the baseline is ``--baseline-tree`` (a checkout of another
commit, e.g. ``git worktree add --detach ../base <commit>``):

    python bench/decode_speed.py --weights run/best.pt --frames test --baseline-tree ../base
    python bench/decode_speed.py --weights onnx/all.onnx onnx/Bread.onnx --frames test --baseline-tree ../base
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _worker(spec_path: str) -> None:
    """One arm (in its own checkout's process): time the decoding of the saved maps; prints
    JSON {weights: {"ms": mean ms per frame, "detections": per frame [[class, score, R, t]]}}."""
    import numpy as np

    from dope_hope.inference.predictor import DopePredictor
    from dope_hope.io.dope_json import find_image, read_dope_json
    from dope_hope.io.images import read_rgb

    spec = json.loads(Path(spec_path).read_text())
    frames = [(read_rgb(find_image(Path(f))), read_dope_json(Path(f)).K) for f in spec["frames"]]
    out = {}
    for weights, maps_file in spec["models"].items():
        extra = {} if spec["min_score"] is None else {"min_score": spec["min_score"]}
        predictor = DopePredictor(weights, threads=1, **extra)
        maps = np.load(maps_file)
        inputs = [(maps[f"b{i}"], maps[f"a{i}"], predictor.prepare(rgb), K) for i, (rgb, K) in enumerate(frames)]
        predictor.detections_from_maps(*inputs[0])  # warm-up (caches, lazy imports)
        found, start = [], time.perf_counter()
        for belief, affinity, net_in, K in inputs:
            found.append(predictor.detections_from_maps(belief, affinity, net_in, K))
        ms = 1000 * (time.perf_counter() - start) / len(inputs)
        out[weights] = {"ms": ms, "detections": [[[d.class_name, round(d.score, 6), np.round(d.R, 6).tolist(),
                                                    np.round(d.t, 6).tolist()] for d in dets] for dets in found]}
    print(json.dumps(out))


def _run_arm(tree: Path, spec: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(spec)], cwd=tree, env=env,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: the decoding run failed ({done.returncode}): "
                         f"{(done.stderr.strip().splitlines() or ['no output'])[-1]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        _worker(sys.argv[2])
        return
    sys.path.insert(0, str(REPO))
    import numpy as np

    from dope_hope.devices import cpu_line
    from dope_hope.errors import DopeHopeError
    from dope_hope.inference.predictor import DopePredictor
    from dope_hope.io.dope_json import find_image, list_dope_frames
    from dope_hope.io.images import read_rgb

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", type=Path, nargs="+", required=True, help="trained models (.pt or .onnx)")
    ap.add_argument("--frames", type=Path, required=True, help="a DOPE-format folder of held-out frames")
    ap.add_argument("--count", type=int, default=100, help="frames used (default 100)")
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds per arm, alternating (default 3)")
    ap.add_argument("--min-score", type=float, help="both arms' min_score (default: the model's / packaged)")
    ap.add_argument("--baseline-tree", type=Path, required=True, help="the baseline's checkout")
    args = ap.parse_args()
    if not (args.baseline_tree / "dope_hope" / "__init__.py").is_file():
        ap.error(f"--baseline-tree {args.baseline_tree}: not a dope-hope checkout (no dope_hope/__init__.py)")
    for w in args.weights:
        if not w.is_file():
            ap.error(f"--weights {w}: no such file")
    if args.count < 1 or args.rounds < 1:
        ap.error("--count and --rounds must be >= 1")
    try:
        frames = list_dope_frames(args.frames)[:args.count]
    except DopeHopeError as exc:
        ap.error(f"--frames: {exc}")
    if not frames:
        ap.error(f"--frames {args.frames}: no DOPE-format frames")
    print(cpu_line())
    print(f"{len(frames)} frames of {args.frames}; baseline {args.baseline_tree.resolve()}, candidate {REPO}")
    with tempfile.TemporaryDirectory() as tmp:
        models = {}
        for k, w in enumerate(args.weights):
            predictor = DopePredictor(w, threads=2)
            maps = {}
            for i, f in enumerate(frames):
                belief, affinity, _ = predictor.infer_maps(read_rgb(find_image(f)))
                maps[f"b{i}"], maps[f"a{i}"] = belief, affinity
            models[str(w.resolve())] = str(Path(tmp) / f"maps{k}.npz")
            np.savez(models[str(w.resolve())], **maps)
        spec = Path(tmp) / "spec.json"
        spec.write_text(json.dumps({"frames": [str(f.resolve()) for f in frames], "models": models,
                                    "min_score": args.min_score}))
        runs: dict[str, list[dict]] = {"baseline": [], "candidate": []}
        for _ in range(args.rounds):
            for arm, tree in (("baseline", args.baseline_tree.resolve()), ("candidate", REPO)):
                runs[arm].append(_run_arm(tree, spec))
    for w in models:
        ms = {arm: statistics.median(r[w]["ms"] for r in rounds) for arm, rounds in runs.items()}
        base, cand = runs["baseline"][0][w]["detections"], runs["candidate"][0][w]["detections"]
        same = sum(b == c for b, c in zip(base, cand))
        print(f"{Path(w).name}: baseline {ms['baseline']:.2f} ms per frame, candidate {ms['candidate']:.2f} ms "
              f"(median of {args.rounds} rounds): candidate / baseline {ms['candidate'] / ms['baseline']:.2f}x; "
              f"detections {sum(map(len, base))} vs {sum(map(len, cand))}, identical on {same} of {len(base)} frames")


if __name__ == "__main__":
    main()
