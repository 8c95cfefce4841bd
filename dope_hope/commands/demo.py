"""See dope-hope estimate 6-DoF poses: the shipped demo model on freshly rendered scenes.

Renders --scenes random 640x480 scenes of the embedded demo box (dope_hope/demo_object.py:
one box at 0.45-0.9 m among a few distractors, RealSense-like depth noise; configs/demo.yaml),
runs the model through PyTorch and through onnxruntime (exported once to OUT/<weights>.onnx
and reused while the weights are unchanged), refines the distance with the depth line search
(-LS), and prints each detection next to the ground truth: translation and rotation error,
ADD-H and MeanSSD without -LS, with -LS and with -LS + ICP (dope_hope/refine/icp.py: the whole
pose refined against the depth), and how closely the ONNX keypoints agree with PyTorch's.
Detections scoring under the model's min score (its own threshold when its file records one,
as the shipped model does, else dope_hope/configs/infer.yaml's; as `dope-hope infer`) are
dropped. Ends with "found N/10 scenes with ADD-H < 2 cm (with -LS; ...)".

The errors and the matching are `dope-hope evaluate`'s (dope_hope/evaluation/matching.py), on
the model evaluate loads from OUT/mesh (500 points of DemoBox.obj, the box's symmetries from
the model_info.json written beside it), so "found N" with -LS is the true-positive count that
`dope-hope evaluate` reports for OUT/predictions.jsonl at 2 cm ADD-H (recall N/10).

Writes OUT/NNNNNN.overlay.png (detection in colour, ground truth in white), OUT/overview.png,
OUT/predictions.jsonl (PyTorch + -LS, the `dope-hope infer` format), OUT/mesh/DemoBox.obj and
OUT/mesh/model_info.json (its symmetries, BOP models_info fields) and
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
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dope_hope.evaluation.matching import PoseErrors

from dope_hope.commands.argtypes import positive_int
from dope_hope.commands.infer import DEMO_WEIGHTS

#: Synth config of the demo scenes (configs/demo.yaml, merged over configs/synth.yaml).
DEMO_CONFIG = "demo"
#: (W, H) of the rendered scenes (the RealSense D415 colour camera's default mode).
IMAGE_SIZE = (640, 480)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--scenes", type=positive_int, default=10, metavar="N", help="scenes to render (default 10)")
    parser.add_argument("--seed", type=int, metavar="S",
                        help="scene seed (default: a fresh random seed, printed so the run can be repeated)")
    parser.add_argument("--out", type=Path, default=Path("demo_out"), metavar="DIR",
                        help="output folder (default ./demo_out)")
    parser.add_argument("--weights", type=Path, metavar="PATH",
                        help="demo checkpoint (default: the shipped dope_hope/assets/demo_lite.pt)")
    parser.add_argument("--no-onnx", action="store_true", help="PyTorch only (no ONNX export and run)")
    parser.add_argument("--threads", type=positive_int, metavar="T", help="CPU threads of each backend")


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
    n_gt: int = 0
    true_positives: int = 0
    lines: list[str] = field(default_factory=list)


def _fmt_t(t) -> str:
    return "(" + ", ".join(f"{100 * v:6.1f}" for v in t) + ") cm"


def _err_text(e: PoseErrors) -> str:
    return (f"dt {e.te_cm:5.2f} cm  dR {e.re_deg:5.1f} deg  ADD-H {e.addh_cm:5.2f} cm  "
            f"MeanSSD {e.meanssd_cm:5.2f} cm")


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
    from dope_hope.errors import ModelFileError
    from dope_hope.io.paths import output_dir

    t_start = time.perf_counter()
    out: Path = output_dir(args.out)
    weights = args.weights if args.weights is not None else DEMO_WEIGHTS
    if args.weights is None and not weights.is_file():
        # the mesh is written on purpose: the message tells how to train a demo model on it
        mesh_path = write_demo_object(out / "mesh")
        raise ModelFileError(DEMO_WEIGHTS, missing_weights_problem(mesh_path))

    from dope_hope.evaluation.models import load_models
    from dope_hope.geometry import cuboid_keypoints, project_points
    from dope_hope.inference.backends import backend_objects, model_min_score, open_backend
    from dope_hope.inference.predictor import DopePredictor
    from dope_hope.io.images import write_rgb
    from dope_hope.io.predictions import write_predictions_jsonl
    from dope_hope.refine.depth import DepthImage
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.writer import write_frame
    from dope_hope.viz import draw_cuboid, draw_label, montage, overlay_detections

    torch_backend = open_backend(weights, "torch", threads=args.threads)  # a bad file stops here
    names = [o.class_name for o in backend_objects(torch_backend)]
    if DEMO_CLASS_NAME not in names:
        raise ModelFileError(weights, f"a model of {', '.join(map(repr, names))}; the demo renders "
                                      f"{DEMO_CLASS_NAME!r} (pass a demo model with --weights)")
    mesh_path = write_demo_object(out / "mesh")
    mesh = demo_object_mesh()
    # The scenes hold the demo object only: a model of several objects reports that one.
    torch_pred = DopePredictor(torch_backend, mesh=mesh, classes=[DEMO_CLASS_NAME])
    _, input_hw = torch_pred.working_size((IMAGE_SIZE[1], IMAGE_SIZE[0]))
    onnx_pred = None
    onnx_note = "ONNX off (--no-onnx)"
    if not args.no_onnx:
        t0 = time.perf_counter()
        onnx_path, exported = ensure_onnx(weights, out, input_hw)
        onnx_pred = DopePredictor(open_backend(onnx_path, "onnx", threads=args.threads), mesh=mesh,
                                  classes=[DEMO_CLASS_NAME])
        onnx_note = (f"ONNX {onnx_path} (" + (f"exported in {time.perf_counter() - t0:.1f} s"
                                              if exported else "cached") + ")")
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % (2 ** 31))
    model = load_models([DEMO_CLASS_NAME], [str(mesh_path)])[DEMO_CLASS_NAME]  # as evaluate loads it
    frames_dir = out / "frames"
    _clear_old_outputs(out)
    print(f"dope-hope demo: {args.scenes} scene(s) of {DEMO_CLASS_NAME}, seed {seed} (repeat with "
          f"--seed {seed}), {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, RealSense-like depth noise; model "
          f"{weights} (network input {input_hw[1]}x{input_hw[0]}, min score {torch_pred.options.min_score:g}"
          f"{', its own' if model_min_score(torch_backend) is not None else ''}); {onnx_note}", flush=True)

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
            _score_scene(res, gts, dets_plain, dets_ls, dets_icp, model)
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
    _print_summary(results, timing, out, mesh_path, time.perf_counter() - t_start, onnx_pred is not None)
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
                 model) -> None:
    """Fill ``res`` (errors, found flags, printed lines) from one scene's detections, matched
    to the ground truth as ``dope-hope evaluate`` matches (:func:`match_frame`: ADD-H below
    2 cm); a scene is found when every instance is."""
    from dope_hope.evaluation.matching import match_frame, pose_errors

    plain, ls, icp = (match_frame(d, gts, model) for d in (dets_plain, dets_ls, dets_icp))
    res.found_no_ls, res.found, res.found_icp = plain.found, ls.found, icp.found
    res.n_gt, res.true_positives = len(gts), int(ls.correct.sum())
    for j, g in enumerate(gts):
        vis = "" if g.visibility is None else f", {100 * g.visibility:.0f} % visible"
        res.lines.append(f"    truth   t {_fmt_t(g.t)}{vis}")
        if ls.estimate_of_gt[j] < 0:
            res.lines.append("    not detected")
            continue
        if plain.estimate_of_gt[j] >= 0:
            d0 = dets_plain[plain.estimate_of_gt[j]]
            res.errors_no_ls = pose_errors(d0.R, d0.t, g, model)
            res.lines.append(f"    PnP     t {_fmt_t(d0.t)}  {_err_text(res.errors_no_ls)}  score {d0.score:.2f}")
        d = dets_ls[ls.estimate_of_gt[j]]
        res.errors = pose_errors(d.R, d.t, g, model)
        ls_note = f"scale {d.ls_scale:.4f}" if d.ls_applied else f"not applied: {d.ls_reason}"
        res.lines.append(f"    PnP+LS  t {_fmt_t(d.t)}  {_err_text(res.errors)}  "
                         + ("OK" if ls.correct[j] else "MISS") + f"  (-LS {ls_note})")
        if icp.estimate_of_gt[j] < 0:
            continue
        d2 = dets_icp[icp.estimate_of_gt[j]]
        res.errors_icp = pose_errors(d2.R, d2.t, g, model)
        icp_note = "applied" if d2.icp_applied else f"not applied: {d2.icp_reason}"
        res.lines.append(f"    +ICP    t {_fmt_t(d2.t)}  {_err_text(res.errors_icp)}  "
                         + ("OK" if icp.correct[j] else "MISS") + f"  (ICP {icp_note})")
    res.extra_detections = ls.unpaired
    if res.extra_detections:
        res.lines.append(f"    + {res.extra_detections} detection(s) without ground truth (false positives)")


def _print_summary(results: list[SceneResult], timing: dict[str, float], out: Path, mesh_path: Path,
                   seconds: float, with_onnx: bool) -> None:
    import numpy as np

    from dope_hope.evaluation.matching import (
        DEFAULT_METRIC,
        METRIC_LABELS,
        TABLE_THRESHOLDS_M,
    )

    n = len(results)
    found = sum(r.found for r in results)
    found0 = sum(r.found_no_ls for r in results)
    found2 = sum(r.found_icp for r in results)
    detected = [r for r in results if r.errors is not None]
    criterion = f"{METRIC_LABELS[DEFAULT_METRIC]} < {100 * TABLE_THRESHOLDS_M[0]:g} cm"
    lines = [f"found {found}/{n} scenes with {criterion} (with -LS; without -LS: {found0}/{n}; "
             f"with -LS + ICP: {found2}/{n})"]
    if detected:
        med = np.median([r.errors.addh_cm for r in detected])
        plain = [r.errors_no_ls.addh_cm for r in detected if r.errors_no_ls is not None]
        med0 = f", {np.median(plain):.2f} cm without" if plain else ""
        medm = np.median([r.errors.meanssd_cm for r in detected])
        with_icp = [r.errors_icp.addh_cm for r in detected if r.errors_icp is not None]
        med2 = f", {np.median(with_icp):.2f} cm with -LS + ICP" if with_icp else ""
        lines.append(f"  median over {len(detected)} detected: ADD-H {med:.2f} cm with -LS{med0}{med2}; "
                     f"MeanSSD {medm:.2f} cm with -LS; "
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
    tp, n_gt = sum(r.true_positives for r in results), sum(r.n_gt for r in results)
    recall = f"{tp / n_gt:.3f}" if n_gt else "n/a"
    lines.append(f"  next: dope-hope evaluate -p {out / 'predictions.jsonl'} -d {out / 'frames'} --mesh "
                 f"{mesh_path} --out {out / 'eval'}\n"
                 f"        (reports recall {recall} at {100 * TABLE_THRESHOLDS_M[0]:g} cm "
                 f"{METRIC_LABELS[DEFAULT_METRIC]}: the {tp} of {n_gt} instances found with -LS)")
    print("\n".join(lines), flush=True)
    sys.stdout.flush()
