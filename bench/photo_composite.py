"""An object composited onto real photographs: recall and false detections, with -LS and without.

Renders the demo box (dope_hope/demo_object.py), or the object of ``--mesh`` (``--object``: its
class in the model, e.g. the HOPE Ketchup for a model that `bench/e2e_accuracy.py` trained),
alone, as `dope-hope demo` renders its scenes
(configs/demo.yaml: one box at 0.45-0.9 m, random lights, the camera's post-processing, but
no distractors; the RealSense D415 colour camera's field of view at every size), over random crops of the photographs in --photos (crop side 60-100 % of the
largest crop of the frame's aspect ratio, rescaled to each --sizes, horizontal flip; the
photo's colours kept). Its depth image: the box's depth in front of a wall at 1.2-3 m (the
photo has none), with the RealSense-like depth noise of the synth config. The synth config's
clutter and hard negatives are off (the photo is the background), and so are its sensor
artefacts (optics, shot noise, JPEG: dope_hope/synth/sensor.py) unless --sensor is given.
Then runs a model (--weights, default the shipped dope_hope/assets/demo_lite.pt) with its
default options but min score 0, without and with the depth line search (-LS), and matches
its detections to the box one-to-one by ADD-H (dope_hope.evaluation.matching: greedy in
descending score, error strictly below the threshold).

Per size and min score (0, the model's default: its own threshold when its file records one, else
configs/infer.yaml's 0.5, and any --min-scores) it prints: the recall
at 2 cm ADD-H (frames whose box is matched), false detections per frame (detections left
unmatched at 2 cm, and at 10 cm: those nowhere near the box), and, on --empty crops of the
same photographs WITHOUT the box, how many frames hold a detection and the detections, both
per 50 frames. -LS moves detections, it never adds or drops one, so the empty-photo figures
hold for both.

    python bench/photo_composite.py --photos PHOTO_OR_FOLDER [...] [--weights W.pt] [--frames 30]
        [--empty 50] [--sizes 640x480 1920x1080] [--seed 0] [--sensor] [--min-scores 0.6 0.7]
        [--preview composites.png] [--mesh MESH --object NAME]
    python bench/photo_composite.py --photos ../shared/data/backgrounds --weights runs/e2e/run/best.pt \
        --mesh ../shared/data/hope_ketchup/textured.obj --object Ketchup --frames 100 --empty 100

The photographs are read in place (photos under a licence stay out of the repository).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import DEMO_CONFIG
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.evaluation.matching import TABLE_THRESHOLDS_M, error_matrix, greedy_match
from dope_hope.evaluation.object_models import load_models
from dope_hope.inference.backends import model_min_score
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.predictor import DopePredictor
from dope_hope.refine.depth import DepthImage
from dope_hope.synth import FrameGenerator
from dope_hope.synth.background import BackgroundSource
from dope_hope.synth.depth_noise import add_realsense_noise, noise_kwargs
from dope_hope.synth.postprocess import post_process
from dope_hope.synth.settings import parse_size

#: Synth config over configs/demo.yaml: the box alone over the photographs, colours untouched.
COMPOSITE_CONFIG = {
    "distractors": {"count": [0, 0], "occluder_prob": 0.0},
    "background": {"procedural_prob_with_images": 0.0, "crop_scale": [0.6, 1.0], "flip_prob": 0.5,
                   "vflip_prob": 0.0,
                   "color_shift": {"brightness": [1.0, 1.0], "contrast": [1.0, 1.0],
                                   "channel_gain": [1.0, 1.0], "channel_offset": 0.0}},
}
#: The RealSense D415 colour camera at any size: fy = 615 px at 480 rows (its 4:3 modes are
#: crops of the 16:9 sensor at the same vertical field of view, so 1920x1080 has fx = fy = 1384).
#: (synth.yaml's own rule scales the 640x480 reference by max(W/640, H/480), i.e. a narrower
#: 1845-px lens at 1920x1080.)
D415_FY_AT_480 = 615.0
#: Distance of the wall behind the box in the depth image, metres.
WALL_DEPTH_M = (1.2, 3.0)
RECALL_THRESHOLD_M, FAR_THRESHOLD_M = TABLE_THRESHOLDS_M  # 2 cm, 10 cm


@dataclass
class Tally:
    """Counts of one (size, -LS or not) cell."""

    frames: int = 0
    found: int = 0          # box matched at 2 cm ADD-H
    found_far: int = 0      # box matched at 10 cm
    false_2cm: int = 0      # detections unmatched at 2 cm
    false_10cm: int = 0     # detections unmatched at 10 cm
    addh_cm: list[float] = field(default_factory=list)  # least ADD-H per frame with a detection

    def add(self, errors: np.ndarray, scores: np.ndarray) -> None:
        """errors: (P, 1) ADD-H metres of the frame's detections against the box."""
        self.frames += 1
        near = greedy_match(errors, scores, RECALL_THRESHOLD_M)
        far = greedy_match(errors, scores, FAR_THRESHOLD_M)
        self.found += int(np.any(near >= 0))
        self.found_far += int(np.any(far >= 0))
        self.false_2cm += int(np.sum(near < 0))
        self.false_10cm += int(np.sum(far < 0))
        if len(scores):
            self.addh_cm.append(100.0 * float(np.min(errors)))


def wall_depth(depth_box: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W) metres: the box's depth where it is rendered, a fronto-parallel wall elsewhere."""
    wall = np.float32(rng.uniform(*WALL_DEPTH_M))
    return np.where(depth_box > 0, depth_box, wall).astype(np.float32)


def run_size(size: tuple[int, int], args: argparse.Namespace, predictor: DopePredictor, model,
             mesh_path: Path, class_name: str, preview: list) -> dict:
    """Composites and empty photos at one (W, H); returns the tallies (per min score and depth
    step) and timings. The predictor keeps every detection (min score 0); each min score in
    ``args.min_scores`` keeps those scoring at least that."""
    tallies = {(m, name): Tally() for m in args.min_scores for name in ("no LS", "LS")}
    empty = {m: {"dets": 0, "frames": 0} for m in args.min_scores}
    t_render = t_model = 0.0
    with FrameGenerator(mesh_path, size=size, config=composite_config(size, args.sensor),
                        class_name=class_name, backgrounds=args.photos, depth_noise=False,
                        seed=args.seed) as gen:
        dn = noise_kwargs(gen.cfg.depth_noise)
        for i in range(args.frames):
            t0 = time.perf_counter()
            frame = gen.render_frame(i)
            rng = np.random.default_rng((args.seed, 1, i))
            depth = add_realsense_noise(wall_depth(frame.depth_clean, rng), frame.rgb, frame.annotation.K, rng, **dn)
            t1 = time.perf_counter()
            K, gt = frame.annotation.K, frame.annotation.objects[0]
            belief, affinity, net_in = predictor.infer_maps(frame.rgb)
            dets = {"no LS": predictor.detections_from_maps(belief, affinity, net_in, K),
                    "LS": predictor.detections_from_maps(belief, affinity, net_in, K,
                                                         DepthImage.from_raw(depth, K, image_hw=frame.rgb.shape[:2]))}
            t2 = time.perf_counter()
            for name, ds in dets.items():
                for m in args.min_scores:
                    kept = [d for d in ds if d.score >= m and d.class_name == class_name]
                    errors = error_matrix("addh", kept, [gt], model, upper=FAR_THRESHOLD_M)
                    tallies[(m, name)].add(errors, np.array([d.score for d in kept]))
            t_render += t1 - t0
            t_model += t2 - t1
            if len(preview) < 8:
                preview.append((frame, dets["LS"]))
        t0 = time.perf_counter()
        for scores in empty_photo_scores(gen, predictor, args.photos, args.empty, args.seed):
            for m in args.min_scores:
                n = sum(sc >= m for sc in scores)
                empty[m]["dets"] += n
                empty[m]["frames"] += int(n > 0)
        t_model += time.perf_counter() - t0
    return {"tallies": tallies, "empty": empty, "render_s": t_render, "model_s": t_model}


def empty_photo_scores(gen: FrameGenerator, predictor: DopePredictor, photos: list[Path], count: int,
                       seed: int) -> list[list[float]]:
    """Scores of the predictor's detections (all false) on ``count`` random crops of the
    photographs without the box: crop, flips and post-processing as the generator ``gen``
    (:func:`composite_config`) composites, each with the camera of composite i."""
    background = BackgroundSource(gen.cfg.background, photos)
    out = []
    for i in range(count):
        rng = np.random.default_rng((seed, 2, i))
        rgb = post_process(rng, background.sample(rng, *gen.size), gen.cfg.post)
        K = gen.sample_scene(i)[0].K  # the camera of a composite (jittered as synth.yaml)
        out.append([d.score for d in predictor.predict(rgb, K)])
    return out


def composite_config(size: tuple[int, int] = (640, 480), sensor: bool = False):
    """configs/synth.yaml < configs/demo.yaml < no clutter, hard negatives or sensor artefacts
    (PLAIN_OVERRIDES) < :data:`COMPOSITE_CONFIG`, with the D415 colour camera at ``size``
    (W, H); with ``sensor`` the sensor artefacts at synth.yaml's probabilities: synth settings."""
    from dope_hope.config import merge
    from dope_hope.synth.sensor import EFFECT_PROBS
    from dope_hope.synth.settings import PLAIN_OVERRIDES, load_synth_config, packaged_synth_config

    f = D415_FY_AT_480 * size[1] / 480.0
    camera = {"camera": {"reference_size": list(size), "fx": f, "fy": f}}
    cfg = merge(merge(merge(load_synth_config(DEMO_CONFIG).to_dict(), PLAIN_OVERRIDES), COMPOSITE_CONFIG), camera)
    if sensor:
        post = packaged_synth_config()["post"]
        cfg = merge(cfg, {"post": {k: post[k] for k in EFFECT_PROBS}})
    return load_synth_config(cfg)


def write_preview(path: Path, preview: list) -> None:
    """Up to 8 composites (-LS detections in colour, the box's true cuboid in white)."""
    from dope_hope.io.images import write_rgb
    from dope_hope.viz import draw_cuboid, montage, overlay_detections

    tiles = []
    for frame, dets in preview:
        img = draw_cuboid(frame.rgb, frame.annotation.objects[0].projected_cuboid, (255, 255, 255),
                          draw_points=False)
        tiles.append(overlay_detections(img, dets, frame.annotation.K))
    write_rgb(path, montage(tiles, cols=4, tile_hw=(240, 320)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", type=Path, nargs="+", required=True,
                    help="photographs: folders and/or image files (read in place)")
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS,
                    help="the model (default: the shipped demo-box model)")
    ap.add_argument("--mesh", type=Path, help="the object's mesh (default: the demo box)")
    ap.add_argument("--object", help="the object's class in the model (default: the demo box's; with "
                    "--mesh, the model's one object)")
    ap.add_argument("--frames", type=int, default=30, help="composites per size (default 30)")
    ap.add_argument("--empty", type=int, default=50, help="photos without the box per size (default 50)")
    ap.add_argument("--sizes", nargs="+", default=["640x480", "1920x1080"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--sensor", action="store_true",
                    help="apply the synth config's sensor artefacts (optics, shot noise, JPEG) to the "
                         "composites and empty photos too")
    ap.add_argument("--min-scores", type=float, nargs="+", default=[], metavar="S",
                    help="more min scores to report, besides 0 and the default")
    ap.add_argument("--preview", type=Path, help="write a montage of the first composites here")
    args = ap.parse_args()

    if args.mesh is not None and not args.mesh.is_file():
        ap.error(f"--mesh {args.mesh}: no such file")
    if args.mesh is None:
        mesh = demo_object_mesh()
    else:  # a mapping names the object of a model of several
        mesh = {args.object: args.mesh} if args.object else args.mesh
    predictor = DopePredictor(args.weights, threads=args.threads, mesh=mesh, min_score=0.0)
    if args.mesh is not None and args.object is None and len(predictor.class_names) > 1:
        ap.error(f"--mesh without --object: {args.weights} has several objects ({', '.join(predictor.class_names)})")
    class_name = args.object or (predictor.class_name if args.mesh else DEMO_CLASS_NAME)
    if class_name not in predictor.class_names:
        ap.error(f"--object {class_name}: not an object of {args.weights} ({', '.join(predictor.class_names)})")
    # The model's default: its own threshold when its file records one, else the packaged one.
    default_min = InferenceOptions.from_mapping({}, model_min_score=model_min_score(predictor.backend)).min_score
    args.min_scores = sorted({0.0, float(default_min), *args.min_scores})
    photos = BackgroundSource(composite_config().background, args.photos).files
    print(f"model {args.weights}, object {class_name}; photos {' '.join(map(str, args.photos))}: {len(photos)} ({', '.join(p.name for p in photos)}); "
          f"{args.frames} composites + {args.empty} empty crops per size, seed {args.seed}; "
          f"min scores {', '.join(f'{m:g}' for m in args.min_scores)} (default {default_min:g}); "
          f"sensor artefacts {'on' if args.sensor else 'off'}", flush=True)
    preview: list = []
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        mesh_path = args.mesh.resolve() if args.mesh else write_demo_object(tmp)
        model = load_models([class_name], [f"{class_name}={mesh_path}"])[class_name]  # as evaluate loads it
        for s in args.sizes:
            size = parse_size(s)
            t0 = time.perf_counter()
            r = run_size(size, args, predictor, model, mesh_path, class_name, preview)
            rows.append((s, r))
            print(f"{s}: done in {time.perf_counter() - t0:.0f} s (render {r['render_s']:.0f} s, "
                  f"model {r['model_s']:.0f} s)", flush=True)
    print("\n| size | min score | depth step | recall @ 2 cm ADD-H | @ 10 cm | median ADD-H of the best "
          "detection (cm) | false detections / frame (unmatched @ 2 cm) | (unmatched @ 10 cm) |")
    print("|---|---|---|---|---|---|---|---|")
    for s, r in rows:
        for (m, name), t in r["tallies"].items():
            med = f"{np.median(t.addh_cm):.2f}" if t.addh_cm else "-"
            print(f"| {s} | {m:g} | {'-LS' if name == 'LS' else 'none'} | {t.found}/{t.frames} = "
                  f"{t.found / max(t.frames, 1):.2f} | {t.found_far / max(t.frames, 1):.2f} | {med} "
                  f"| {t.false_2cm / max(t.frames, 1):.2f} | {t.false_10cm / max(t.frames, 1):.2f} |")
    print("\n| size | min score | photos without the box | with a false detection | per 50 frames "
          "| false detections per 50 frames |")
    print("|---|---|---|---|---|---|")
    for s, r in rows:
        n = max(args.empty, 1)
        for m, e in r["empty"].items():
            print(f"| {s} | {m:g} | {args.empty} | {e['frames']} | {50.0 * e['frames'] / n:.1f} "
                  f"| {50.0 * e['dets'] / n:.1f} |")
    if args.preview is not None and preview:
        write_preview(args.preview, preview)
        print(f"\npreview: {args.preview}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
