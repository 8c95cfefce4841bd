"""The whole demo (:func:`run_demo`): render the scenes, run the model through PyTorch and
onnxruntime, refine with -LS and -LS + ICP, score, draw and write; the lines to show are
handed to the caller (``dope-hope demo`` prints them)."""
from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.demo.onnx_cache import ensure_onnx
from dope_hope.demo.report import SceneResult, backend_agreement, next_steps, score_scene, summary_lines
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE, DemoScene, render_scene
from dope_hope.demo_object import DEMO_CLASS_NAME, DEMO_SIZE_M, demo_object_mesh, write_demo_object
from dope_hope.errors import ModelFileError
from dope_hope.evaluation.object_models import load_models
from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.inference import backends  # looked up at each call: a substituted open_backend counts
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.images import write_rgb
from dope_hope.io.paths import output_dir
from dope_hope.io.predictions import write_predictions_jsonl
from dope_hope.refine.depth import DepthImage
from dope_hope.synth import FrameGenerator
from dope_hope.synth.writer import write_frame
from dope_hope.viz import draw_cuboid, draw_label, montage, overlay_detections


@dataclass
class DemoSettings:
    """One demo run: ``scenes`` scenes of ``seed`` (None: a fresh random seed) into ``out``
    with the model at ``weights``; ``onnx``: also through onnxruntime; ``threads``: CPU
    threads of each backend (None: the backend's default); ``options``: inference options
    over the defaults (:class:`~dope_hope.inference.options.InferenceOptions`; min_score: the
    model's own unless given)."""

    weights: Path
    out: Path
    scenes: int = 10
    seed: int | None = None
    onnx: bool = True
    threads: int | None = None
    options: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Models:
    """The opened predictors and what the first printed line says about them."""

    torch_pred: object
    onnx_pred: object | None
    note: str
    input_hw: tuple[int, int]
    own_min_score: bool
    mesh_path: Path
    model: object  # evaluation ObjectModel, as evaluate loads it
    timing: dict[str, float] = field(default_factory=lambda: {"render": 0.0, "torch": 0.0, "icp": 0.0, "onnx": 0.0})


def _open_models(settings: DemoSettings, out: Path) -> _Models:
    """The backends before any rendering (torch imported after the GL context crashes on some
    machines); a model of another object is refused."""
    torch_backend = backends.open_backend(settings.weights, "torch", threads=settings.threads)  # a bad file stops here
    names = [o.class_name for o in backends.backend_objects(torch_backend)]
    if DEMO_CLASS_NAME not in names:
        raise ModelFileError(settings.weights, f"a model of {', '.join(map(repr, names))}; the demo renders "
                                               f"{DEMO_CLASS_NAME!r} (pass a demo model with --weights)")
    mesh_path = write_demo_object(out / "mesh")
    mesh = demo_object_mesh()
    # The scenes hold the demo object only: a model of several objects reports that one.
    torch_pred = DopePredictor(torch_backend, mesh=mesh, classes=[DEMO_CLASS_NAME], options=settings.options)
    _, input_hw = torch_pred.working_size((IMAGE_SIZE[1], IMAGE_SIZE[0]))
    onnx_pred, note = None, "ONNX off (--no-onnx)"
    if settings.onnx:
        t0 = time.perf_counter()
        onnx_path, exported = ensure_onnx(settings.weights, out, input_hw)
        onnx_pred = DopePredictor(backends.open_backend(onnx_path, "onnx", threads=settings.threads), mesh=mesh,
                                  classes=[DEMO_CLASS_NAME], options=settings.options)
        note = f"ONNX {onnx_path} (" + (f"exported in {time.perf_counter() - t0:.1f} s" if exported else "cached") + ")"
    model = load_models([DEMO_CLASS_NAME], [str(mesh_path)])[DEMO_CLASS_NAME]
    return _Models(torch_pred, onnx_pred, note, input_hw, torch_pred.own_min_score, mesh_path, model)


def clear_old_outputs(out: Path) -> None:
    """Remove the frames and overlays an earlier demo run wrote (OUT/frames/NNNNNN.{png,json,
    depth.png,seg.png} and OUT/NNNNNN.overlay.png only), so that OUT holds exactly this run's
    scenes."""
    for folder, pattern in ((out / "frames", r"^\d{6}\.(png|json|depth\.png|seg\.png)$"),
                            (out, r"^\d{6}\.overlay\.png$")):
        if folder.is_dir():
            for p in folder.iterdir():
                if p.is_file() and re.match(pattern, p.name):
                    p.unlink()


def _run_scene(m: _Models, scene: DemoScene, name: str) -> tuple[SceneResult, list]:
    """Both backends, -LS and -LS + ICP on one scene, scored: (result, the -LS detections)."""
    frame = scene.frame
    K, gts = frame.annotation.K, frame.annotation.objects
    t0 = time.perf_counter()
    belief, affinity, net_in = m.torch_pred.infer_maps(frame.rgb)
    depth = DepthImage.from_raw(frame.depth, K, image_hw=frame.rgb.shape[:2])
    dets_plain = m.torch_pred.detections_from_maps(belief, affinity, net_in, K)
    dets_ls = m.torch_pred.detections_from_maps(belief, affinity, net_in, K, depth=depth)
    m.timing["torch"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    dets_icp = [m.torch_pred.refine_icp(d, depth) for d in dets_ls]
    m.timing["icp"] += time.perf_counter() - t0
    res = SceneResult(name=name, measurable=scene.measurable)
    if m.onnx_pred is not None:
        t0 = time.perf_counter()
        res.onnx_diff_px = backend_agreement(dets_plain, m.onnx_pred.predict(frame.rgb, K))
        m.timing["onnx"] += time.perf_counter() - t0
    score_scene(res, gts, dets_plain, dets_ls, dets_icp, m.model)
    return res, dets_ls


def _scene_header(i: int, n: int, scene: DemoScene, res: SceneResult, n_dets: int) -> str:
    header = f"[{i + 1:>{len(str(n))}}/{n}] {res.name}: {n_dets} detection(s)"
    if scene.draws > 1:
        header += (f"; scene drawn {scene.draws} times for a box at least half visible" if scene.measurable else
                   f"; the box stayed {100 * scene.visibility:.0f} % visible in {scene.draws} draws: "
                   f"left out of the count")
    if res.onnx_diff_px is not None:
        header += (f"; ONNX keypoints within {res.onnx_diff_px:.3f} px of PyTorch"
                   if math.isfinite(res.onnx_diff_px) else "; ONNX found other objects than PyTorch")
    return header


def _overlay(scene: DemoScene, res: SceneResult, dets_ls: list) -> np.ndarray:
    """The scene with the ground truth in white under the -LS detections and a verdict label."""
    img, K = scene.frame.rgb, scene.frame.annotation.K
    for g in scene.frame.annotation.objects:
        img = draw_cuboid(img, project_points(cuboid_keypoints(DEMO_SIZE_M), K, g.R, g.t),
                          (255, 255, 255), draw_points=False)
    img = overlay_detections(img, dets_ls, K)
    verdict = ("no detection" if res.errors is None else
               f"ADD-H {res.errors.addh_cm:.2f} cm (-LS) {'OK' if res.found else 'MISS'}")
    return draw_label(img, f"{res.name}  {verdict}  (ground truth: white)", (4, IMAGE_SIZE[1] - 24))


def run_demo(settings: DemoSettings, show: Callable[[str], None]) -> list[SceneResult]:
    """Run the demo (see ``dope-hope demo --help``); ``show`` gets the header, each scene's
    lines and the summary as they come. Writes OUT/NNNNNN.overlay.png, OUT/overview.png,
    OUT/predictions.jsonl (PyTorch + -LS), OUT/mesh/ and OUT/frames/ (DOPE format)."""
    t_start = time.perf_counter()
    out = output_dir(settings.out)
    m = _open_models(settings, out)
    seed = settings.seed if settings.seed is not None else int(np.random.SeedSequence().entropy % (2 ** 31))
    clear_old_outputs(out)
    show(f"dope-hope demo: {settings.scenes} scene(s) of {DEMO_CLASS_NAME}, seed {seed} (repeat with --seed "
         f"{seed}), {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, box at least half visible, RealSense-like depth noise; "
         f"model {settings.weights} (network input {m.input_hw[1]}x{m.input_hw[0]}, min score "
         f"{m.torch_pred.objects[0].min_score:g}{', its own' if m.own_min_score else ''}); {m.note}")
    results, records, tiles = [], [], []
    with FrameGenerator(m.mesh_path, size=IMAGE_SIZE, config=DEMO_CONFIG, class_name=DEMO_CLASS_NAME,
                        depth_noise=True, seed=seed) as gen:
        for i in range(settings.scenes):
            t0 = time.perf_counter()
            scene = render_scene(gen, i)
            write_frame(out / "frames", i, scene.frame.rgb, scene.frame.depth, scene.frame.seg,
                        scene.frame.annotation, extra=gen.json_extra(scene.frame, seed=scene.seed))
            m.timing["render"] += time.perf_counter() - t0
            res, dets_ls = _run_scene(m, scene, f"{i:06d}.png")
            results.append(res)
            records += [d.to_json(res.name) for d in dets_ls]
            show("\n".join([_scene_header(i, settings.scenes, scene, res, len(dets_ls))] + res.lines))
            tiles.append(_overlay(scene, res, dets_ls))
            write_rgb(out / f"{i:06d}.overlay.png", tiles[-1])
    write_rgb(out / "overview.png", montage(tiles, cols=min(5, len(tiles)),
                                            tile_hw=(IMAGE_SIZE[1] // 2, IMAGE_SIZE[0] // 2)))
    write_predictions_jsonl(out / "predictions.jsonl", records)
    t = m.timing
    show("\n".join(summary_lines(results, m.onnx_pred is not None)
                   + [f"  time {time.perf_counter() - t_start:.1f} s (rendering {t['render']:.1f} s, PyTorch + -LS "
                      f"{t['torch']:.1f} s, ICP {t['icp']:.1f} s" + (f", ONNX {t['onnx']:.1f} s" if m.onnx_pred else "")
                      + ")"]
                   + next_steps(results, out, m.mesh_path)))
    return results
