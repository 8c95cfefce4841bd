"""See dope-hope estimate 6-DoF poses: the shipped demo model on freshly rendered scenes.

Renders --scenes random 640x480 scenes of the embedded demo box (dope_hope/demo_object.py:
one box at 0.45-0.9 m among a few distractors, RealSense-like depth noise; configs/demo.yaml),
runs the model through PyTorch and through onnxruntime (exported once to OUT/<weights>.onnx
and reused while the weights are unchanged), refines the distance with the depth line search
(-LS), and prints each detection next to the ground truth: translation and rotation error,
ADD-H and MeanSSD (500 model points, the box's declared symmetries) without -LS, with -LS
and with -LS + ICP (dope_hope/refine/icp.py: the whole pose refined against the depth), and how
closely the ONNX keypoints agree with PyTorch's. Ends with
"found N/10 scenes with ADD-H < 2 cm (with -LS; ...)".

Writes OUT/NNNNNN.overlay.png (detection in colour, ground truth in white), OUT/overview.png,
OUT/predictions.jsonl (PyTorch + -LS, the `dope-hope infer` format), OUT/mesh/DemoBox.obj and
OUT/frames/NNNNNN.{png,depth.png,seg.png,json} (DOPE format), so that
  dope-hope infer OUT/frames/000000.png --depth auto
  dope-hope evaluate -p OUT/predictions.jsonl -d OUT/frames --mesh OUT/mesh/DemoBox.obj
work on them. Exit status 0 whatever the accuracy; 2 when it cannot run (e.g. no weights).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dope_hope.commands.infer import DEMO_WEIGHTS

#: Synth config of the demo scenes (configs/demo.yaml, merged over configs/synth.yaml).
DEMO_CONFIG = "demo"
#: (W, H) of the rendered scenes (the RealSense D415 colour camera's default mode).
IMAGE_SIZE = (640, 480)
#: A scene counts as found when its object's ADD-H is below this, centimetres.
THRESHOLD_CM = 2.0
#: Model points of ADD-H / MeanSSD (the HOPE paper's 500).
MODEL_POINTS = 500


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--scenes", type=int, default=10, metavar="N", help="scenes to render (default 10)")
    parser.add_argument("--seed", type=int, metavar="S",
                        help="scene seed (default: a fresh random seed, printed so the run can be repeated)")
    parser.add_argument("--out", type=Path, default=Path("demo_out"), metavar="DIR",
                        help="output folder (default ./demo_out)")
    parser.add_argument("--weights", type=Path, metavar="PATH",
                        help="demo checkpoint (default: the shipped dope_hope/assets/demo_lite.pt)")
    parser.add_argument("--no-onnx", action="store_true", help="PyTorch only (no ONNX export and run)")
    parser.add_argument("--threads", type=int, metavar="T", help="CPU threads of each backend")


# ----------------------------------------------------------------------------- helpers
def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def ensure_onnx(weights: Path, out_dir: Path, input_hw: tuple[int, int]) -> tuple[Path, bool]:
    """Export ``weights`` to ``out_dir/<stem>.onnx`` at the fixed input (H, W) unless an export
    of the same weights (SHA-256) at that size is already there. Returns (path, exported)."""
    from dope_hope import __version__
    from dope_hope.export.pipeline import export_checkpoint
    from dope_hope.io.atomic import atomic_write_text

    onnx_path = out_dir / f"{weights.stem}.onnx"
    stamp_path = out_dir / f"{weights.stem}.onnx.json"
    stamp = {"weights_sha256": file_sha256(weights), "input_hw": [int(v) for v in input_hw],
             "dope_hope_version": __version__}
    if onnx_path.is_file() and stamp_path.is_file():
        try:
            if json.loads(stamp_path.read_text(encoding="utf-8")) == stamp:
                return onnx_path, False
        except (OSError, json.JSONDecodeError):
            pass
    export_checkpoint(weights, onnx_path, height=int(input_hw[0]), width=int(input_hw[1]))
    atomic_write_text(stamp_path, json.dumps(stamp, indent=1) + "\n")
    return onnx_path, True


@dataclass
class PoseErrors:
    """Errors of one pose against its ground truth: te (cm), symmetry-aware re (deg), ADD-H
    and MeanSSD (cm)."""

    te_cm: float
    re_deg: float
    addh_cm: float
    meanssd_cm: float


def pose_errors(R, t, R_gt, t_gt, points, symmetries) -> PoseErrors:
    """``points`` (N, 3) model points (m); ``symmetries`` (S, 4, 4) model-frame transforms."""
    import numpy as np

    from dope_hope.evaluation.metrics import addh, mean_ssd, re, te

    rot = min(re(R, R_gt @ S[:3, :3]) for S in np.asarray(symmetries))
    return PoseErrors(te_cm=100.0 * te(t, t_gt), re_deg=rot,
                      addh_cm=100.0 * addh(R, t, R_gt, t_gt, points),
                      meanssd_cm=100.0 * mean_ssd(R, t, R_gt, t_gt, points, symmetries))


def keypoint_difference(a, b) -> float:
    """Largest distance (px) between the keypoints two backends found (finite in both);
    inf when one found a keypoint the other did not."""
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    fa, fb = np.isfinite(a).all(axis=1), np.isfinite(b).all(axis=1)
    if np.any(fa != fb):
        return math.inf
    if not fa.any():
        return 0.0
    return float(np.max(np.linalg.norm(a[fa] - b[fa], axis=1)))


def backend_agreement(dets_a: list, dets_b: list) -> float:
    """Max keypoint difference (px) between two backends' detections of one image, matched in
    score order; inf when they found different numbers of objects."""
    if len(dets_a) != len(dets_b):
        return math.inf
    return max([keypoint_difference(a.keypoints_2d, b.keypoints_2d) for a, b in zip(dets_a, dets_b)],
               default=0.0)


@dataclass
class SceneResult:
    """What the demo found in one scene (PyTorch backend)."""

    name: str
    found: bool = False
    found_no_ls: bool = False
    found_icp: bool = False
    errors: PoseErrors | None = None
    errors_no_ls: PoseErrors | None = None
    errors_icp: PoseErrors | None = None
    onnx_diff_px: float | None = None
    extra_detections: int = 0
    lines: list[str] = field(default_factory=list)


def _fmt_t(t) -> str:
    return "(" + ", ".join(f"{100 * v:6.1f}" for v in t) + ") cm"


def _err_text(e: PoseErrors) -> str:
    return (f"dt {e.te_cm:5.2f} cm  dR {e.re_deg:5.1f} deg  ADD-H {e.addh_cm:5.2f} cm  "
            f"MeanSSD {e.meanssd_cm:5.2f} cm")


def match_detections(dets: list, gts: list) -> list[tuple[Any, Any]]:
    """Greedy matching in descending score: each detection takes the nearest free GT instance
    (centre distance). Returns (gt, det or None) for every GT, in GT order."""
    import numpy as np

    free = list(range(len(gts)))
    pairs: dict[int, Any] = {}
    for d in sorted(dets, key=lambda d: -d.score):
        if not free:
            break
        j = min(free, key=lambda k: float(np.linalg.norm(np.asarray(d.t) - gts[k].t)))
        pairs[j] = d
        free.remove(j)
    return [(g, pairs.get(k)) for k, g in enumerate(gts)]


def missing_weights_problem(mesh_path: Path) -> str:
    """What to do when the shipped demo model is absent (one line)."""
    return (f"demo model not found (this installation ships none); train one with the commands "
            f"in configs/demo.yaml (the demo mesh is written to {mesh_path}) and pass --weights "
            f"runs/demo/best.pt")


# ----------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    import numpy as np

    from dope_hope.demo_object import (
        DEMO_CLASS_NAME,
        DEMO_SIZE_M,
        demo_object_mesh,
        write_demo_object,
    )
    from dope_hope.errors import ConfigError, ModelFileError

    t_start = time.perf_counter()
    if args.scenes < 1:
        raise ConfigError(f"--scenes must be at least 1, got {args.scenes}")
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be at least 1, got {args.threads}")
    out: Path = args.out
    mesh_path = write_demo_object(out / "mesh")
    weights = args.weights if args.weights is not None else DEMO_WEIGHTS
    if not weights.is_file():
        if args.weights is None:
            raise ModelFileError(DEMO_WEIGHTS, missing_weights_problem(mesh_path))
        raise ModelFileError(weights, "weights file not found")

    from dope_hope.geometry import cuboid_keypoints, project_points
    from dope_hope.inference.backends import open_backend
    from dope_hope.inference.predictor import DopePredictor
    from dope_hope.io.images import write_rgb
    from dope_hope.io.meshes import sample_surface_points
    from dope_hope.io.predictions import write_predictions_jsonl
    from dope_hope.refine.depth import DepthImage
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.writer import write_frame
    from dope_hope.viz import draw_cuboid, draw_label, montage, overlay_detections

    mesh = demo_object_mesh()
    torch_backend = open_backend(weights, "torch", threads=args.threads)
    if torch_backend.class_name != DEMO_CLASS_NAME:
        raise ModelFileError(weights, f"a model of {torch_backend.class_name!r}; the demo renders "
                                      f"{DEMO_CLASS_NAME!r} (pass a demo model with --weights)")
    torch_pred = DopePredictor(torch_backend, mesh=mesh)
    _, input_hw = torch_pred.working_size((IMAGE_SIZE[1], IMAGE_SIZE[0]))
    onnx_pred = None
    onnx_note = "ONNX off (--no-onnx)"
    if not args.no_onnx:
        t0 = time.perf_counter()
        onnx_path, exported = ensure_onnx(weights, out, input_hw)
        onnx_pred = DopePredictor(open_backend(onnx_path, "onnx", threads=args.threads), mesh=mesh)
        onnx_note = (f"ONNX {onnx_path} (" + (f"exported in {time.perf_counter() - t0:.1f} s"
                                              if exported else "cached") + ")")
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % (2 ** 31))
    points = sample_surface_points(mesh, MODEL_POINTS, seed=0)
    from dope_hope.io.symmetries import declared_symmetries

    symmetries = declared_symmetries(mesh_path=mesh_path).transforms()  # model_info.json beside it
    frames_dir = out / "frames"
    _clear_old_outputs(out)
    print(f"dope-hope demo: {args.scenes} scene(s) of {DEMO_CLASS_NAME}, seed {seed} (repeat with "
          f"--seed {seed}), {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, RealSense-like depth noise; model "
          f"{weights} (network input {input_hw[1]}x{input_hw[0]}); {onnx_note}", flush=True)

    results: list[SceneResult] = []
    records: list[dict] = []
    tiles = []
    timing = {"render": 0.0, "torch": 0.0, "icp": 0.0, "onnx": 0.0}
    with FrameGenerator(mesh_path, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME,
                        depth_noise=True, seed=seed) as gen:
        for i in range(args.scenes):
            t0 = time.perf_counter()
            frame = gen.render_frame(i)
            write_frame(frames_dir, i, frame.rgb, frame.depth, frame.seg, frame.annotation,
                        extra=gen.json_extra(frame))
            timing["render"] += time.perf_counter() - t0
            K, gts = frame.annotation.K, frame.annotation.objects
            t0 = time.perf_counter()
            belief, affinity, net_in = torch_pred.infer_maps(frame.rgb)
            depth = DepthImage.from_raw(frame.depth, K, image_hw=frame.rgb.shape[:2])
            dets_plain = torch_pred.detections_from_maps(belief, affinity, net_in, K)
            dets_ls = torch_pred.detections_from_maps(belief, affinity, net_in, K, depth=depth)
            timing["torch"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            dets_icp = [torch_pred.refine_icp(d, depth) for d in dets_ls]
            timing["icp"] += time.perf_counter() - t0
            res = SceneResult(name=f"{i:06d}.png")
            if onnx_pred is not None:
                t0 = time.perf_counter()
                dets_onnx = onnx_pred.predict(frame.rgb, K)
                timing["onnx"] += time.perf_counter() - t0
                res.onnx_diff_px = backend_agreement(dets_plain, dets_onnx)
            _score_scene(res, gts, dets_plain, dets_ls, dets_icp, points, symmetries)
            results.append(res)
            records += [d.to_json(res.name) for d in dets_ls]
            header = (f"[{i + 1:>{len(str(args.scenes))}}/{args.scenes}] {res.name}: "
                      f"{len(dets_ls)} detection(s)")
            if res.onnx_diff_px is not None:
                header += (f"; ONNX keypoints within {res.onnx_diff_px:.3f} px of PyTorch"
                           if math.isfinite(res.onnx_diff_px) else "; ONNX found other objects than PyTorch")
            print("\n".join([header] + res.lines), flush=True)
            # Overlay: ground truth in white under the detections (-LS poses).
            img = frame.rgb
            for g in gts:
                img = draw_cuboid(img, project_points(cuboid_keypoints(DEMO_SIZE_M), K, g.R, g.t),
                                  (255, 255, 255), draw_points=False)
            img = overlay_detections(img, dets_ls, K)
            verdict = ("no detection" if res.errors is None else
                       f"ADD-H {res.errors.addh_cm:.2f} cm (-LS) {'OK' if res.found else 'MISS'}")
            img = draw_label(img, f"{res.name}  {verdict}  (ground truth: white)", (4, IMAGE_SIZE[1] - 24))
            write_rgb(out / f"{i:06d}.overlay.png", img)
            tiles.append(img)
    write_rgb(out / "overview.png", montage(tiles, cols=min(5, len(tiles)),
                                            tile_hw=(IMAGE_SIZE[1] // 2, IMAGE_SIZE[0] // 2)))
    write_predictions_jsonl(out / "predictions.jsonl", records)
    _print_summary(results, timing, out, time.perf_counter() - t_start, onnx_pred is not None)
    return 0


def _clear_old_outputs(out: Path) -> None:
    """Remove the frames and overlays an earlier demo run wrote (OUT/frames/NNNNNN.{png,json,
    depth.png,seg.png} and OUT/NNNNNN.overlay.png only), so that OUT holds exactly this run's
    scenes."""
    import re

    for folder, pattern in ((out / "frames", r"^\d{6}\.(png|json|depth\.png|seg\.png)$"),
                            (out, r"^\d{6}\.overlay\.png$")):
        if folder.is_dir():
            for p in folder.iterdir():
                if p.is_file() and re.match(pattern, p.name):
                    p.unlink()


def _score_scene(res: SceneResult, gts: list, dets_plain: list, dets_ls: list, dets_icp: list,
                 points, symmetries) -> None:
    """Fill ``res`` (errors, found flags, printed lines) from one scene's detections."""
    matched_ls = match_detections(dets_ls, gts)
    matched_plain = dict((id(g), d) for g, d in match_detections(dets_plain, gts))
    matched_icp = dict((id(g), d) for g, d in match_detections(dets_icp, gts))
    all_ls = all_icp = True
    used = 0
    for g, d in matched_ls:
        vis = "" if g.visibility is None else f", {100 * g.visibility:.0f} % visible"
        res.lines.append(f"    truth   t {_fmt_t(g.t)}{vis}")
        d0 = matched_plain.get(id(g))
        if d is None or d0 is None:
            res.lines.append("    not detected")
            continue
        used += 1
        e0 = pose_errors(d0.R, d0.t, g.R, g.t, points, symmetries)
        e1 = pose_errors(d.R, d.t, g.R, g.t, points, symmetries)
        res.errors, res.errors_no_ls = e1, e0
        res.found_no_ls = e0.addh_cm < THRESHOLD_CM
        res.found = e1.addh_cm < THRESHOLD_CM
        all_ls &= res.found
        res.lines.append(f"    PnP     t {_fmt_t(d0.t)}  {_err_text(e0)}  score {d0.score:.2f}")
        ls_note = f"scale {d.ls_scale:.4f}" if d.ls_applied else f"not applied: {d.ls_reason}"
        res.lines.append(f"    PnP+LS  t {_fmt_t(d.t)}  {_err_text(e1)}  "
                         + ("OK" if res.found else "MISS") + f"  (-LS {ls_note})")
        d2 = matched_icp.get(id(g))
        if d2 is None:
            all_icp = False
            continue
        e2 = pose_errors(d2.R, d2.t, g.R, g.t, points, symmetries)
        res.errors_icp = e2
        res.found_icp = e2.addh_cm < THRESHOLD_CM
        all_icp &= res.found_icp
        icp_note = "applied" if d2.icp_applied else f"not applied: {d2.icp_reason}"
        res.lines.append(f"    +ICP    t {_fmt_t(d2.t)}  {_err_text(e2)}  "
                         + ("OK" if res.found_icp else "MISS") + f"  (ICP {icp_note})")
    res.extra_detections = len(dets_ls) - used
    if res.extra_detections:
        res.lines.append(f"    + {res.extra_detections} detection(s) without ground truth (false positives)")
    if len(gts) > 1:  # found = every instance within the threshold
        res.found = all_ls and used == len(gts)
        res.found_icp = all_icp and used == len(gts)


def _print_summary(results: list[SceneResult], timing: dict[str, float], out: Path, seconds: float,
                   with_onnx: bool) -> None:
    import numpy as np

    n = len(results)
    found = sum(r.found for r in results)
    found0 = sum(r.found_no_ls for r in results)
    found2 = sum(r.found_icp for r in results)
    detected = [r for r in results if r.errors is not None]
    lines = [f"found {found}/{n} scenes with ADD-H < {THRESHOLD_CM:g} cm (with -LS; without -LS: {found0}/{n}; "
             f"with -LS + ICP: {found2}/{n})"]
    if detected:
        med = np.median([r.errors.addh_cm for r in detected])
        med0 = np.median([r.errors_no_ls.addh_cm for r in detected])
        medm = np.median([r.errors.meanssd_cm for r in detected])
        with_icp = [r.errors_icp.addh_cm for r in detected if r.errors_icp is not None]
        med2 = f", {np.median(with_icp):.2f} cm with -LS + ICP" if with_icp else ""
        lines.append(f"  median over {len(detected)} detected: ADD-H {med:.2f} cm with -LS, {med0:.2f} cm "
                     f"without{med2}; MeanSSD {medm:.2f} cm with -LS; "
                     f"{sum(r.extra_detections for r in results)} false positive(s)")
    if with_onnx:
        diffs = [r.onnx_diff_px for r in results]
        same = sum(math.isfinite(d) for d in diffs)
        worst = max((d for d in diffs if math.isfinite(d)), default=0.0)
        lines.append(f"  ONNX vs PyTorch: same objects in {same}/{n} scenes, keypoints within {worst:.3f} px")
    lines.append(f"  time {seconds:.1f} s (rendering {timing['render']:.1f} s, PyTorch + -LS "
                 f"{timing['torch']:.1f} s, ICP {timing['icp']:.1f} s"
                 + (f", ONNX {timing['onnx']:.1f} s" if with_onnx else "") + ")")
    lines.append(f"  overlays: {out}/NNNNNN.overlay.png, {out / 'overview.png'}; frames: {out / 'frames'}")
    lines.append(f"  next: dope-hope infer {out / 'frames' / '000000.png'} --depth auto --out {out / 'infer'}")
    print("\n".join(lines), flush=True)
    sys.stdout.flush()
