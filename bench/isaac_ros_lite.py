"""Lite head 100 (stride 4) in the Isaac ROS layout: accuracy of the in-graph resampling.

Renders the scenes of `dope-hope demo` (configs/demo.yaml, 640x480; the frames of
`dope-hope demo --seed S --scenes N`, keeping those whose box is less than half visible,
which the demo draws again) and runs the demo model (stride-4 maps) at its working
size three ways:

* **native**: PyTorch, stride-4 maps, dope-hope's decoder and pose search (no -LS);
* **isaac-ros file**: the model exported with ``--layout isaac-ros`` for
  ``--isaac-ros-version`` (2x2 average pooling to stride 8 in the graph, channels in Isaac's
  vertex order), run with onnxruntime and read back by dope-hope's OnnxBackend + predictor;
* **Isaac ROS decoder**: the same file's output decoded by the transcription of Isaac ROS's
  DOPE decoder (``dope_hope.export.isaac_ros.decode``): the pose Isaac ROS would publish.

Keypoint drift of the resampling alone, native stride-4 maps against the same maps after 2x2
average pooling (what the graph does) or 2x2 max pooling (for comparison), at stride 8:
**peaks**: every belief peak (``find_peaks``, image px) matched one-to-one to the pooled
map's peaks of its channel within one pooled cell (8 network px); **object**: the keypoints of
the decoded instance (``decode_maps``) nearest the box against those of the pooled maps'
instance nearest it. Network-input px and 640x480 px. Pose accuracy: ADD-H (cm, the demo's and
`dope-hope evaluate`'s model: 500 points, the box's declared symmetries; detections matched to
the box as `evaluate` matches, dope_hope/evaluation/matching.py; a scene is found below 2 cm)
and the symmetry-aware rotation error against the ground truth.

    python bench/isaac_ros_lite.py [--seed 0] [--scenes 10] [--isaac-ros-version 4.0]
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE
from dope_hope.demo_object import (
    DEMO_CLASS_NAME,
    demo_object_mesh,
    write_demo_object,
)
from dope_hope.evaluation.matching import TABLE_THRESHOLDS_M, match_frame, pose_errors
from dope_hope.evaluation.object_models import load_models
from dope_hope.export.isaac_ros import ISAAC_ROS_CURRENT, isaac_ros_release
from dope_hope.export.isaac_ros import decode as isaac_decode
from dope_hope.export.pipeline import export_checkpoint
from dope_hope.export.to_onnx import ExportSettings
from dope_hope.geometry import scale_intrinsics
from dope_hope.inference.backends import open_backend
from dope_hope.inference.onnx_backend import OnnxBackend
from dope_hope.inference.predictor import DopePredictor
from dope_hope.maps.decode import decode_maps
from dope_hope.maps.grid import map_to_image
from dope_hope.maps.peaks import find_peaks
from dope_hope.synth import FrameGenerator


def pooled(maps: np.ndarray, how: str) -> np.ndarray:
    """(C, h, w) -> (C, h/2, w/2) by 2x2 average or max pooling."""
    t = torch.from_numpy(np.ascontiguousarray(maps))[None]
    f = torch.nn.functional.avg_pool2d if how == "avg" else torch.nn.functional.max_pool2d
    return f(t, 2)[0].numpy()


def peak_drift(belief: np.ndarray, pooled_belief: np.ndarray) -> tuple[list[float], int]:
    """(distances of the matched peaks, network px; native peaks without a match)."""
    a, b = find_peaks(belief, noise_sigmas=0.0), find_peaks(pooled_belief, noise_sigmas=0.0)  # every peak
    out, missing = [], 0
    for c in range(9):
        pa = map_to_image(a.xy[a.channel == c], 4)
        pb = map_to_image(b.xy[b.channel == c], 8)
        if not len(pa):
            continue
        if not len(pb):
            missing += len(pa)
            continue
        d = np.linalg.norm(pa[:, None] - pb[None], axis=2)
        rows, cols = linear_sum_assignment(d)
        keep = d[rows, cols] <= 8.0
        out += d[rows, cols][keep].tolist()
        missing += len(pa) - int(keep.sum())
    return out, missing


def matched(instances, centroid: np.ndarray):
    """The decoded instance whose centroid is nearest ``centroid`` (2,) px (or None)."""
    best, dist = None, np.inf
    for inst in instances:
        d = np.linalg.norm(inst.keypoints[8] - centroid)
        if np.isfinite(d) and d < dist:
            best, dist = inst, d
    return best


def summary(d: list[float]) -> str:
    a = np.asarray(d)
    return (f"median {np.median(a):.3f}, p95 {np.percentile(a, 95):.3f}, max {a.max():.3f}"
            if a.size else "none")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--isaac-ros-version", default=ISAAC_ROS_CURRENT)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    tmp = Path(tempfile.mkdtemp(prefix="isaac-lite-"))
    mesh_path = write_demo_object(tmp / "mesh")
    mesh = demo_object_mesh()
    # min_score 0 throughout: every detection, as the figures in bench/RESULTS.md were measured.
    pred = DopePredictor(open_backend(args.weights, "torch", threads=args.threads), mesh=mesh, min_score=0.0)
    if pred.stride != 4:
        raise SystemExit(f"{args.weights}: stride {pred.stride}, this bench is about stride-4 models")
    resized, padded = pred.working_size((IMAGE_SIZE[1], IMAGE_SIZE[0]))
    scale = IMAGE_SIZE[0] / resized[1]  # 640x480 px per network px
    release = isaac_ros_release(args.isaac_ros_version)
    onnx_path = tmp / "isaac.onnx"
    res = export_checkpoint(args.weights, onnx_path,
                            ExportSettings(layout="isaac-ros", isaac_ros_version=args.isaac_ros_version,
                                           input_hw=(padded[0], padded[1])))
    isaac_backend = OnnxBackend(onnx_path, threads=args.threads, providers=["CPUExecutionProvider"])
    dims_cm = json.loads(res.info.extra["isaac_ros.object_dimensions_cm"])
    print(f"{args.weights}: stride {pred.stride}, network input {padded[1]}x{padded[0]} (content "
          f"{resized[1]}x{resized[0]}, x{scale:.2f} to 640x480); Isaac ROS {release.version} "
          f"export {onnx_path.name}; {args.scenes} demo scenes, seed {args.seed}")

    model = load_models([DEMO_CLASS_NAME], [str(mesh_path)])[DEMO_CLASS_NAME]  # as evaluate loads it
    isaac_pred = DopePredictor(isaac_backend, mesh=mesh, min_score=0.0)
    pools = ("avg", "max")
    drift: dict[str, list[float]] = {f"{p} {w}": [] for p in pools for w in ("peaks", "object")}
    lost = {k: 0 for k in drift}
    errors: dict[str, list] = {"native": [], "isaac-ros file": [], f"Isaac ROS {release.version} decoder": []}
    graph_max_abs = 0.0
    with FrameGenerator(mesh_path, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME,
                        depth_noise=True, seed=args.seed) as gen:
        for i in range(args.scenes):
            frame = gen.render_frame(i)
            K, gt = frame.annotation.K, frame.annotation.objects[0]
            belief, affinity, net_in = pred.infer_maps(frame.rgb)
            b8, a8, net8 = isaac_pred.infer_maps(frame.rgb)
            graph_max_abs = max(graph_max_abs, float(np.abs(b8 - pooled(belief, "avg")).max()),
                                float(np.abs(a8 - pooled(affinity, "avg")).max()))
            gt_centroid = (gt.projected_cuboid[8] + 0.5) / scale - 0.5  # network px
            ref = matched(decode_maps(belief, affinity, 4), gt_centroid)
            for p in pools:
                d, missing = peak_drift(belief, pooled(belief, p))
                drift[f"{p} peaks"] += d
                lost[f"{p} peaks"] += missing
                if ref is None:
                    continue
                t = matched(decode_maps(pooled(belief, p), pooled(affinity, p), 8), ref.keypoints[8])
                ok_ref = np.isfinite(ref.keypoints[:, 0])
                ok = ok_ref & (np.isfinite(t.keypoints[:, 0]) if t is not None else False)
                lost[f"{p} object"] += int((ok_ref & ~ok).sum())
                if t is not None:
                    drift[f"{p} object"] += np.linalg.norm(t.keypoints[ok] - ref.keypoints[ok], axis=1).tolist()
            dets = {"native": pred.detections_from_maps(belief, affinity, net_in, K),
                    "isaac-ros file": isaac_pred.detections_from_maps(b8, a8, net8, K)}
            for name, d in dets.items():
                k = match_frame(d, [gt], model).estimate_of_gt[0]
                errors[name].append(None if k < 0 else pose_errors(d[k].R, d[k].t, gt, model))
            out = isaac_backend.session.run(None, isaac_backend.feeds(net_in.batch)[0])[0]
            K_net = scale_intrinsics(K, 1 / scale, 1 / scale)
            poses = isaac_decode(out, K_net, dims_cm, release)
            best = min(poses, key=lambda q: np.linalg.norm(q[1] - gt.t)) if poses else None
            errors[f"Isaac ROS {release.version} decoder"].append(
                None if best is None else pose_errors(best[0], best[1], gt, model))
    print(f"isaac-ros graph output vs 2x2 average pool of the native maps: max |d| {graph_max_abs:.2e}")
    print("\nkeypoint drift of the resampling (stride-4 maps vs pooled, decoded at stride 8):")
    for k, d in drift.items():
        px = np.asarray(d)
        print(f"  {k:>11}: network px {summary(px)}; 640x480 px {summary(px * scale)}; "
              f"{px.size} compared, {lost[k]} unmatched")
    print(f"\npose accuracy, {args.scenes} scenes (no -LS):")
    for name, errs in errors.items():
        got = [e for e in errs if e is not None]
        found = sum(e.addh_cm < 100 * TABLE_THRESHOLDS_M[0] for e in got)
        print(f"  {name:>26}: found {found}/{args.scenes} (ADD-H < {100 * TABLE_THRESHOLDS_M[0]:g} cm), "
              f"{len(got)} with a pose; ADD-H cm {summary([e.addh_cm for e in got])}; "
              f"rotation deg {summary([e.re_deg for e in got])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
