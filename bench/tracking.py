"""Tracking on video: raw per-frame poses against tracked ones (`dope-hope infer CLIP --track`).

    nice -n 10 python bench/tracking.py [--frames 60] [--threads 2] [--quick] [--tracking JSON]

Renders four clips of the demo box (dope_hope/demo_object.py) at 640x480 and 30 frames/s with
the demo scenes' camera, lights, background and distractors (configs/demo.yaml; distractors
that would cover the box's path are left out), per-frame camera noise (Gaussian pixel noise,
RealSense-like depth noise) and ground truth per frame:

* ``resting``: the box still, only the camera's noise changes;
* ``moving``: the box swings sideways, x = A sin(w t), at up to 0.5 m/s, turning +-17 deg
  about the vertical;
* ``crossing``: two boxes pass each other (0.3 and 0.4 m over the clip: 0.15 and 0.2 m/s at
  60 frames), the nearer one in front;
* ``occluded``: the box passes behind a post (0.4 m over the clip), fully hidden for a few
  frames.

The moving box is motion-blurred as a camera exposing half a frame would see it: the
rendered foreground is smeared along the box's image motion over half its per-frame step.

Each clip is written as an mp4v video (MJPG .avi where mp4v is missing) with its depth kept,
then played through the loop of `dope-hope infer clip.mp4` (run_stream on the file, every
frame: network through onnxruntime with ``--threads`` threads, decode + PnP, -LS on the depth,
JSON records, overlay video), once raw and once with the :class:`PoseTracker` after the
predictor (`--track`), alternating. Reported, raw vs tracked:

* jitter on ``resting``: the standard deviation of the pose error's change from one frame
  to the next (translation: root of the summed per-axis variances of the change of
  t - t_gt, mm; rotation: of the change of the error's rotation vector after the
  symmetries, deg); beside it the error's standard deviation over the frames, which also
  holds the estimate's slow wander (the demo model's pose switches between nearby PnP
  solutions for several frames at a time);
* per-frame recall at 2 cm MeanSSD per clip: ground-truth boxes matched as `dope-hope evaluate`
  matches (greedy by score, dope_hope.evaluation.matching.match_frame) by a published pose
  (raw: every detection; tracked: every record, coasted ones included), over every frame,
  hidden ones too;
* lag on ``moving``: the mean error along the direction of motion over the frames where the
  box moves faster than 0.25 m/s, in frames of motion (positive: behind);
* identity switches: changes of the track id matched to each ground-truth box (within 5 cm)
  between the frames it is matched in (raw detections carry no ids);
* frames/s end to end over all clips (run_stream's count), and the tracker's own time per
  frame (PoseTracker.update: association, filter, the coasted poses' line search).

``--quick``: 24 frames per clip. Targets: jitter >= 3x lower, recall >= 10 points higher on
moving and occluded, no identity switch on crossing, >= 15 frames/s tracked.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from video_with_depth import VideoWithDepth

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.devices import cpu_line
from dope_hope.inference.frame_loop import passive_openmp
from dope_hope.io.camera import ImageCamera

FPS = 30.0
SIZE = (640, 480)
SEED = 7000  # never used for training (demo_lite: seeds 1, 2) or other benches
CLIPS = ("resting", "moving", "crossing", "occluded")
MATCH_M = 0.02       # recall threshold, MeanSSD
IDENTITY_M = 0.05    # a track "is" a ground-truth box when its translation is this close
TARGETS = {"jitter": 3.0, "recall_points": 10.0, "fps": 15.0}


@dataclass
class Clip:
    """A rendered clip: video file, K, per-frame depth (metres) and ground truth
    (per frame: list of (R (3, 3), t (3,)) per box, in a fixed box order)."""

    name: str
    video: Path
    K: np.ndarray
    depths: list[np.ndarray]
    gt: list[list[tuple[np.ndarray, np.ndarray]]]


@dataclass
class Played:
    """One loop over a clip: per frame the published objects; the stream's stats."""

    objects: list[list] = field(default_factory=list)
    fps: float = 0.0
    frames: int = 0
    seconds: float = 0.0
    tracker_seconds: float = 0.0


# ----------------------------------------------------------------------------- motions
def _turn(deg: float, axis: str = "y") -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def box_paths(clip: str, n: int, R0: np.ndarray) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per frame, the poses (R, t) of the boxes of ``clip`` (camera frame, metres)."""
    frames = []
    for k in range(n):
        s = k / FPS
        if clip == "resting":
            boxes = [(R0, np.array([0.02, 0.01, 0.6]))]
        elif clip == "moving":  # x = A sin(w s), peak speed A w = 0.5 m/s
            A, w = 0.15, 0.5 / 0.15
            boxes = [(_turn(17.0 * np.sin(w * s)) @ R0, np.array([A * np.sin(w * s), 0.0, 0.62]))]
        elif clip == "crossing":  # from -0.15 / +0.2 m to +0.15 / -0.2 m over the clip
            u = 2.0 * k / (n - 1) - 1.0
            boxes = [(R0, np.array([0.15 * u, 0.03, 0.55])), (_turn(35.0) @ R0, np.array([-0.2 * u, -0.03, 0.75]))]
        else:  # occluded: from -0.2 to +0.2 m behind a post at x = 0 (see occluder())
            u = 2.0 * k / (n - 1) - 1.0
            boxes = [(R0, np.array([0.2 * u, 0.0, 0.65]))]
        frames.append(boxes)
    return frames


def occluder(n_frames: int):
    """The post of the ``occluded`` clip: a (trimesh box, centre (3,)) in front of the path."""
    import trimesh

    return trimesh.creation.box(extents=[0.07, 0.24, 0.02]), np.array([0.0, 0.0, 0.4])


# ----------------------------------------------------------------------------- rendering
def _disc(K: np.ndarray, center: np.ndarray, radius: float) -> tuple[np.ndarray, float]:
    """Projected centre (2,) px and radius px of a sphere."""
    uv = (K @ center)[:2] / center[2]
    return uv, float(K[0, 0] * radius / center[2])


def _scene_for(base, target_spec, poses, K, extra) -> list:
    """The objects of one frame: the boxes at ``poses``, the kept distractors, ``extra``."""
    from dataclasses import replace

    c_model = target_spec.R.T @ (target_spec.center - target_spec.t)
    boxes = [replace(target_spec, seg_id=i + 1, R=R, t=t, center=R @ c_model + t) for i, (R, t) in enumerate(poses)]
    return boxes + base + extra


def _kept_distractors(spec, target_spec, paths, K) -> list:
    """The scene's distractors whose image discs never come near a box's (20 px margin)."""
    kept = []
    c_model = target_spec.R.T @ (target_spec.center - target_spec.t)
    for o in spec.objects:
        if o.role == "target":
            continue
        uv, r = _disc(K, o.center, o.radius)
        near = False
        for poses in paths:
            for R, t in poses:
                uv_b, r_b = _disc(K, R @ c_model + t, target_spec.radius)
                near |= bool(np.linalg.norm(uv - uv_b) < r + r_b + 20)
        if not near:
            kept.append(o)
    return kept


def render_clip(gen, clip: str, n: int, out: Path) -> Clip:
    """Render ``clip`` (n frames) with the demo scene of seed SEED + its index; write the video."""
    import cv2

    from dope_hope.synth.background import BackgroundSource
    from dope_hope.synth.depth_noise import add_realsense_noise, noise_kwargs
    from dope_hope.synth.materials import MeshBuilder
    from dope_hope.synth.postprocess import composite
    from dope_hope.synth.render import SceneRenderer
    from dope_hope.synth.scene import MaterialSpec, ObjectSpec

    spec, streams, targets, _ = gen.sample_scene(0, seed=SEED + CLIPS.index(clip))
    (target,), (target_spec,) = targets, spec.targets  # the demo box, once
    K = spec.K
    paths = box_paths(clip, n, target_spec.R)
    base = _kept_distractors(spec, target_spec, paths, K)
    extra = []
    if clip == "occluded":
        geometry, centre = occluder(n)
        extra.append(ObjectSpec(role="distractor", seg_id=250, R=np.eye(3), t=centre, radius=0.14, center=centre,
                                source="primitive", geometry=geometry,
                                material=MaterialSpec(np.array([0.55, 0.5, 0.45, 1.0]), 0.0, 0.8)))
    background = BackgroundSource(gen.cfg.background, None).sample(streams["background"], *SIZE)
    builder = MeshBuilder()
    rng = np.random.default_rng(SEED + 100 + CLIPS.index(clip))
    depths, writer, video = [], None, None
    with SceneRenderer(*SIZE, shadows=bool(gen.cfg.lights.shadows)) as renderer:
        for k, poses in enumerate(paths):
            spec.objects = _scene_for(base, target_spec, poses, K, extra)
            r = renderer.render(spec, lambda o: builder.target(target, o.material) if o.source == "target"
                                else builder.primitive_mesh(o.geometry, o.material),
                                (target.cuboid_size, target.cuboid_center))
            color, alpha = r.color, r.alpha
            if clip == "moving":
                step = _disc(K, poses[0][1], 0.0)[0] - _disc(K, paths[max(k - 1, 0)][0][1], 0.0)[0]
                color, alpha = motion_blur(color, alpha, 0.5 * step)
            rgb = composite(background, color, alpha).astype(np.float32)
            rgb = np.clip(rgb + rng.normal(0.0, 3.0, rgb.shape), 0, 255).astype(np.uint8)
            depths.append(add_realsense_noise(r.depth, rgb, K, rng, **noise_kwargs(gen.cfg.depth_noise))
                          .astype(np.float32))
            if writer is None:
                for suffix, fourcc in ((".mp4", "mp4v"), (".avi", "MJPG")):
                    video = out / f"{clip}{suffix}"
                    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*fourcc), FPS, SIZE)
                    if writer.isOpened():
                        break
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return Clip(clip, video, K, depths, paths)


def motion_blur(color: np.ndarray, alpha: np.ndarray, step_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) colour and (H, W) alpha of a foreground render smeared along ``step_px`` (2,)."""
    import cv2

    n = int(round(float(np.linalg.norm(step_px))))
    if n < 2:
        return color, alpha
    size = 2 * n + 1
    kernel = np.zeros((size, size), np.float32)
    for s in np.linspace(-0.5, 0.5, 4 * n):
        kernel[int(round(n + s * step_px[1])), int(round(n + s * step_px[0]))] = 1.0
    kernel /= kernel.sum()
    # the render's colour is premultiplied by its coverage (synth.postprocess.composite)
    return (cv2.filter2D(color.astype(np.float32), -1, kernel),
            cv2.filter2D(alpha.astype(np.float32), -1, kernel))


# ----------------------------------------------------------------------------- playing
def play(predictor, clip: Clip, tracked: bool, out: Path, max_frames: int | None = None,
         settings: dict | None = None) -> Played:
    """The `dope-hope infer clip.mp4 [--track]` loop over a clip (records, overlay video)."""
    from dope_hope.inference.stream_inference import StreamSinks, predict_stream
    from dope_hope.inference.tracking import PoseTracker
    from dope_hope.io.video import OverlayVideo

    camera = ImageCamera(K=clip.K, width=SIZE[0], height=SIZE[1], source=Path("bench"))
    source = VideoWithDepth(clip.video, camera, clip.depths)
    overlay = OverlayVideo(out / f"{clip.name}_{'tracked' if tracked else 'raw'}.overlay", FPS)
    played, lines = Played(), []
    tracker = None
    if tracked:
        tracker = PoseTracker(predictor, settings={**predictor.options.tracking.to_dict(), **(settings or {})})
        update = tracker.update

        def timed_update(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return update(*args, **kwargs)
            finally:
                played.tracker_seconds += time.perf_counter() - t0

        tracker.update = timed_update  # the tracker's own share of the loop's time
    sinks = StreamSinks(on_record=lambda rec: lines.append(json.dumps(rec)),
                        on_frame=lambda frame, objs: played.objects.append(objs), video=overlay)
    stats = predict_stream(source, [predictor], sinks, tracker=tracker, max_frames=max_frames).stats
    overlay.close()
    played.fps, played.frames, played.seconds = stats.fps, stats.processed, stats.seconds
    return played


# ----------------------------------------------------------------------------- figures
def _gts(poses) -> list:
    from dope_hope.annotation import ObjectAnnotation

    return [ObjectAnnotation(DEMO_CLASS_NAME, R, t) for R, t in poses]


def recall(clip: Clip, played: Played, model) -> float:
    """Percent of ground-truth boxes over all frames matched below MATCH_M MeanSSD."""
    from dope_hope.evaluation.matching import match_frame

    found = total = 0
    for poses, objs in zip(clip.gt, played.objects):
        total += len(poses)
        if objs:
            found += int(match_frame(objs, _gts(poses), model, metric="meanssd", threshold=MATCH_M).correct.sum())
    return 100.0 * found / max(total, 1)


def jitter(clip: Clip, played: Played, model) -> dict[str, float]:
    """The pose error of the estimate paired with the (first) box, as evaluate pairs them at
    any error: ``t_step`` (mm) / ``R_step`` (deg): standard deviation of its change from one
    frame to the next (root of the summed per-axis variances; consecutive frames with an
    estimate); ``t_std`` / ``R_std``: its standard deviation over the frames; ``frames``."""
    from dope_hope.inference.pose_filter import closest_equivalent

    errors: list[tuple[int, np.ndarray, np.ndarray]] = []
    for k, (poses, objs) in enumerate(zip(clip.gt, played.objects)):
        est = _matched(poses, objs, model)
        if est is None:
            continue
        R_gt, t_gt = poses[0]
        R_e = closest_equivalent(np.asarray(est.R), np.asarray(est.t), R_gt, model.symmetries)[0]
        errors.append((k, 1000.0 * (np.asarray(est.t) - t_gt),
                       np.degrees(Rotation.from_matrix(R_e @ R_gt.T).as_rotvec())))

    def spread(vectors) -> float:
        return float(np.sqrt(np.var(vectors, axis=0).sum())) if len(vectors) >= 2 else float("nan")

    steps = [(b[1] - a[1], b[2] - a[2]) for a, b in zip(errors, errors[1:]) if b[0] == a[0] + 1]
    return {"t_step": spread([s[0] for s in steps]), "R_step": spread([s[1] for s in steps]),
            "t_std": spread([e[1] for e in errors]), "R_std": spread([e[2] for e in errors]),
            "frames": len(errors)}


def _matched(poses, objs, model):
    """The published object paired with the first box (as evaluate pairs, at any error), or None."""
    from dope_hope.evaluation.matching import match_frame

    if not objs:
        return None
    m = match_frame(objs, _gts(poses[:1]), model, metric="meanssd", threshold=MATCH_M)
    return None if m.estimate_of_gt[0] < 0 else objs[int(m.estimate_of_gt[0])]


def lag_frames(clip: Clip, played: Played, model) -> float:
    """Mean error along the motion, in frames of motion (positive: behind), over the frames
    where the first box moves faster than 0.25 m/s."""
    lags = []
    for k in range(1, len(clip.gt)):
        v = clip.gt[k][0][1] - clip.gt[k - 1][0][1]
        est = _matched(clip.gt[k], played.objects[k], model)
        if est is None or np.linalg.norm(v) * FPS < 0.25:
            continue
        lags.append(-float((np.asarray(est.t) - clip.gt[k][0][1]) @ v) / float(v @ v))
    return float(np.mean(lags)) if lags else float("nan")


def identity_switches(clip: Clip, played: Played) -> tuple[int, int]:
    """(switches, frames with a matched track) over every box of the clip."""
    switches = matched = 0
    for g in range(len(clip.gt[0])):
        last = None
        for poses, objs in zip(clip.gt, played.objects):
            t_gt = poses[g][1]
            near = [(float(np.linalg.norm(np.asarray(o.t) - t_gt)), o.track_id) for o in objs]
            near = [x for x in near if x[0] < IDENTITY_M]
            if not near:
                continue
            tid = min(near)[1]
            matched += 1
            switches += int(last is not None and tid != last)
            last = tid
    return switches, matched


# ----------------------------------------------------------------------------- main
def open_predictor(weights: Path, threads: int, tmp: Path):
    """The demo model through onnxruntime (exported at the clips' working size) with the
    demo mesh; before any rendering (torch after the GL context crashes here)."""
    from dope_hope.export.pipeline import export_checkpoint
    from dope_hope.export.to_onnx import ExportSettings
    from dope_hope.inference.backends import open_backend
    from dope_hope.inference.predictor import DopePredictor

    mesh = demo_object_mesh()
    torch_pred = DopePredictor(open_backend(weights, "torch", threads=threads), mesh=mesh)
    _, input_hw = torch_pred.working_size((SIZE[1], SIZE[0]))
    onnx_path = tmp / f"{weights.stem}.onnx"
    export_checkpoint(weights, onnx_path, ExportSettings(input_hw=(int(input_hw[0]), int(input_hw[1]))))
    return DopePredictor(open_backend(onnx_path, "onnx", threads=threads), mesh=mesh), input_hw


def measure(clips: list[Clip], predictor, tmp: Path, model, settings: dict | None = None) -> dict[str, dict]:
    """Play every clip raw and tracked (alternating); the figures of each."""
    res: dict[str, dict] = {"raw": {}, "tracked": {}}
    play(predictor, clips[0], False, tmp, max_frames=5)  # warm-up: first runs, caches
    for clip in clips:
        for mode in ("raw", "tracked"):
            p = play(predictor, clip, mode == "tracked", tmp, settings=settings)
            r = res[mode]
            r[f"recall_{clip.name}"] = recall(clip, p, model)
            r["frames"] = r.get("frames", 0) + p.frames
            r["seconds"] = r.get("seconds", 0.0) + p.seconds
            r["tracker_seconds"] = r.get("tracker_seconds", 0.0) + p.tracker_seconds
            if clip.name == "resting":
                r["jitter"] = jitter(clip, p, model)
            if clip.name == "moving":
                r["lag"] = lag_frames(clip, p, model)
            if mode == "tracked":
                r[f"switches_{clip.name}"] = identity_switches(clip, p)
            print(f"{clip.name:9s} {mode:7s}: {p.frames} frames, {p.fps:.1f} frames/s, recall "
                  f"{r[f'recall_{clip.name}']:.1f} %, load average {os.getloadavg()[0]:.2f}", flush=True)
    for r in res.values():
        r["fps"] = r["frames"] / r["seconds"] if r["seconds"] > 0 else 0.0
    return res


def report(res: dict[str, dict], clips: list[Clip]) -> None:
    raw, trk = res["raw"], res["tracked"]
    print("\nfigure                          raw        tracked    ratio / difference")
    if "jitter" in raw:
        a, b = raw["jitter"], trk["jitter"]
        for key, label in (("t_step", "jitter resting, t (mm)     "), ("R_step", "jitter resting, R (deg)    "),
                           ("t_std", "error std resting, t (mm)  "), ("R_std", "error std resting, R (deg) ")):
            print(f"{label}    {a[key]:8.2f}   {b[key]:8.2f}    {a[key] / b[key]:.1f}x lower")
    for clip in clips:
        a, b = raw[f"recall_{clip.name}"], trk[f"recall_{clip.name}"]
        print(f"recall @2cm MeanSSD {clip.name:9s}  {a:7.1f} %  {b:7.1f} %   {b - a:+.1f} points")
    if "lag" in raw:
        print(f"lag moving (frames)            {raw['lag']:8.2f}   {trk['lag']:8.2f}")
    for clip in clips:
        sw, n = trk[f"switches_{clip.name}"]
        print(f"identity switches {clip.name:9s}   no ids     {sw:5d}      ({n} box-frames tracked)")
    print(f"frames/s end to end            {raw['fps']:8.1f}   {trk['fps']:8.1f}    "
          f"{trk['fps'] / raw['fps']:.2f}x")
    ms = 1000.0 * trk["tracker_seconds"] / max(trk["frames"], 1)
    print(f"tracker (PoseTracker.update)   {'':8s}   {ms:8.2f} ms per frame, "
          f"{100.0 * trk['tracker_seconds'] / trk['seconds']:.1f} % of the tracked loop's time")
    ok = []
    if "jitter" in raw:
        for key in ("t_step", "R_step"):
            met = raw["jitter"][key] / trk["jitter"][key] >= TARGETS["jitter"]
            ok.append(f"jitter {key[0]} {'meets' if met else 'misses'}")
    for name in ("moving", "occluded"):
        if f"recall_{name}" in raw:
            gain = trk[f"recall_{name}"] - raw[f"recall_{name}"]
            ok.append(f"recall {name} {'meets' if gain >= TARGETS['recall_points'] else 'misses'}")
    if "switches_crossing" in trk:
        ok.append(f"crossing {'meets' if trk['switches_crossing'][0] == 0 else 'misses'}")
    ok.append(f"fps {'meets' if trk['fps'] >= TARGETS['fps'] else 'misses'}")
    print("targets: " + ", ".join(ok))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames per clip")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    ap.add_argument("--clips", nargs="+", choices=CLIPS, default=list(CLIPS))
    ap.add_argument("--quick", action="store_true", help="24 frames per clip")
    ap.add_argument("--keep", type=Path, help="keep the clips and overlay videos in this folder")
    ap.add_argument("--tracking", type=json.loads, default={}, metavar="JSON",
                    help='tracker settings over configs/infer.yaml\'s, e.g. \'{"max_coast": 10}\'')
    args = ap.parse_args()
    n = 24 if args.quick else args.frames

    passive_openmp()  # as `dope-hope infer` does for a stream, before torch is imported
    from dope_hope.config import config_path, load_yaml, merge
    from dope_hope.evaluation.object_models import load_models
    from dope_hope.synth import FrameGenerator

    with tempfile.TemporaryDirectory(prefix="bench-tracking-") as tmpdir:
        tmp = args.keep or Path(tmpdir)
        tmp.mkdir(parents=True, exist_ok=True)
        predictor, input_hw = open_predictor(args.weights, args.threads, tmp)
        mesh_path = write_demo_object(tmp / "mesh")
        model = load_models([DEMO_CLASS_NAME], [str(mesh_path)])[DEMO_CLASS_NAME]
        cfg = merge(load_yaml(config_path("demo")),
                    {"camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}})
        t0 = time.perf_counter()
        with FrameGenerator(mesh_path, size=SIZE, config=cfg, class_name=DEMO_CLASS_NAME, seed=SEED) as gen:
            clips = [render_clip(gen, name, n, tmp) for name in args.clips]
        print(f"{cpu_line()}, {os.cpu_count()} CPUs, {args.threads} threads; {len(clips)} clips x {n} frames "
              f"{SIZE[0]}x{SIZE[1]} rendered in {time.perf_counter() - t0:.1f} s; {args.weights.name} through "
              f"onnxruntime at {input_hw[1]}x{input_hw[0]}; load average {os.getloadavg()[0]:.2f}", flush=True)
        if args.tracking:
            print(f"tracking settings: {json.dumps(args.tracking)}", flush=True)
        res = measure(clips, predictor, tmp, model, args.tracking)
    report(res, clips)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
