"""One network for six objects against six one-object networks, at the same CPU budget.

The six objects are real textured meshes: the HOPE Ketchup (cm) and the five grocery objects
of the shared data (``grocery_objects/``: Bread, Can, Cereal, Lemon, Milk; metres). Stages
(each a `dope-hope` command run as a subprocess, as a user types it; logged to OUT/logs/):

1. ``synth-train``: one training set of the six objects (seed 1, at the lite input size
   256x192, the packaged configs/synth.yaml with :data:`TRAIN_TARGETS`: zero to four of the
   six per frame, so frames without any target are negatives; ``--train-scene-set`` overrides
   it, e.g. two to four as in the held-out scenes). No photograph.
2. ``train-all``: one six-object lite network (`dope-hope train --object ... --mesh ...`)
   for T minutes from the shipped pretrained start; ``train-<Name>``: six one-object lite
   networks, T/6 minutes each, on the same frames (the other five objects are clutter to
   them), also from the pretrained start. Same frames, same total wall-clock budget. Both
   train symmetry-aware labels (:data:`TRAIN_SET`, ``targets.symmetry=auto``): the Ketchup
   its catalog category's, the five grocery meshes the symmetries found on them
   (``dope_hope.symmetry.detect``, printed at the start: the can and the lemon turn about
   their axis, the cereal box flips about its three axes, the milk carton and the loaf
   about their long one).
3. ``synth-test``: held-out 640x480 frames (seed 1001) with two to four of the objects each
   (:data:`TEST_SCENE`), a real photo background (the shared ``backgrounds/``, which no
   training frame uses) and RealSense-like depth noise.
4. ``infer-all`` / ``infer-six``: `dope-hope infer --fast --depth auto` (the depth line search,
   "-LS", on each object's mesh: ``--mesh NAME=PATH --mesh-units NAME=UNIT``) with the one
   model, and with the six models (one ``--weights`` each); ``infer-all-icp`` /
   ``infer-six-icp`` the same with ``--icp`` (-LS + ICP).
5. ``eval-all`` / ``eval-six`` (and ``-icp``): `dope-hope evaluate --metric meanssd`: recall at 2 cm
   MeanSSD per object and their mean, with the same symmetries; then, in this process, where
   each arm loses the held-out instances, per object (no detection, beyond 10 cm, within 10 cm
   but not 2 cm, within 2 cm; at score >= 0.5, at the threshold each object's training run
   chose on its validation frames (what `infer` keeps by default), at each object's own
   threshold from `calibrate` and at every score: :func:`shelf_losses`).
5b. Each object's own threshold, as a user calibrates a model: ``synth-calib`` renders other
   frames like the held-out ones (seed :data:`CALIB_SEED`, ``--calib-count``),
   ``infer-calib-all`` / ``infer-calib-six`` run both arms on them with no threshold,
   ``calibrate-all`` / ``calibrate-<Name>`` (`dope-hope calibrate`) record each object's F1
   threshold with the weights (OUT/calibrated/), and ``infer-all-own`` / ``infer-six-own`` run
   the calibrated weights on the held-out frames at their own thresholds (no --min-score).
6. ``export-*`` and, in this process, the time per frame with onnxruntime (2 threads): the
   whole pipeline of `DopePredictor` on each test image (forward pass, decoding, PnP; no
   depth), the one model against a one-object model and against the six one-object models
   in turn, frame by frame (side by side), and the frames per second of the one model.

Targets (issue "Many objects, one network"): the one model's mean recall >= the six models'
at the same budget; its time per frame <= 1.3x a one-object model's; >= 15 frames/s. The
recall ranks every detection; the loss breakdown shows what a user's `infer` keeps: at the
default 0.5 and at each object's calibrated threshold.

Prints the CPU line, the tables and the ratios; writes OUT/results.md and OUT/results.json.
Resumable at stage granularity (OUT/stages/<stage>.json markers; training resumes with
--resume); OUT/e2e_settings.json refuses a rerun with other settings in the same folder.

    python bench/multi_object.py                                  # T = 60 min on 2 CPU cores
    python bench/multi_object.py --minutes 20 --out bench/out/multi_object_20
    python bench/multi_object.py --quick --out /tmp/mo_quick       # every stage, tiny: numbers meaningless
    python bench/multi_object.py --one-model-set model.lite.stage_channels=96 --out bench/out/mo_wide
    python bench/multi_object.py --train-scene-set 'target.count=[2,4]' --out bench/out/mo_2to4
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e_accuracy import (  # noqa: E402
    LOSS_CLASSES,
    REPO,
    TEST_SEED,
    TRAIN_SEED,
    check_settings,
    checkpoint_of,
    instance_losses,
    loss_counts,
    percent_text,
    set_args,
    shared_data_dir,
)

from dope_hope.devices import cpu_description, cpu_line  # noqa: E402
from dope_hope.staged_run import CommandStages  # noqa: E402
from dope_hope.synth.settings import PLAIN_OVERRIDES  # noqa: E402

#: The objects: class -> (mesh path relative to the shared data folder, its unit).
OBJECTS = {"Bread": ("grocery_objects/Bread/textured.obj", "m"), "Can": ("grocery_objects/Can/textured.obj", "m"),
           "Cereal": ("grocery_objects/Cereal/textured.obj", "m"), "Ketchup": ("hope_ketchup/textured.obj", "cm"),
           "Lemon": ("grocery_objects/Lemon/textured.obj", "m"), "Milk": ("grocery_objects/Milk/textured.obj", "m")}
#: Targets of the training frames: zero to four of the six (a frame draws which), at table-top range.
TRAIN_TARGETS = ["target.count=[0,4]", "target.distance_m=[0.35,0.8]"]
#: The held-out scenes: two to four of the objects, plain (no clutter backgrounds, look-alikes or
#: sensor artefacts), over a photo background given by --backgrounds.
TEST_SCENE = ["target.count=[2,4]", "target.distance_m=[0.35,0.8]", *set_args(PLAIN_OVERRIDES)]
#: The seed of the frames each object's threshold is calibrated on (neither trained nor tested on).
CALIB_SEED = 2002
#: Where the loss breakdown is counted: (label, the suffix of the arm's inference folder, min
#: score; None: each object's threshold its training run recorded, which a user's `infer`
#: keeps by default): at 0.5 (infer's default without one), at the run's thresholds, at each
#: object's own from `calibrate` (the calibrated weights, run at their thresholds), and every
#: detection (as the recall ranks them).
BREAKDOWNS = (("score >= 0.5", "", 0.5), ("the threshold its training chose", "", None),
              ("each object's own threshold", "_own", 0.0), ("every score", "", 0.0))
#: The arms: (label, the folder suffix of their inference, their evaluate method).
ARMS = (("one six-object model", "all", "one-model-LS"), ("six one-object models", "six", "six-models-LS"))
#: Training overrides: symmetry-aware labels (each object's symmetries: the catalog category's,
#: else those found on its mesh).
TRAIN_SET = ["targets.symmetry=auto"]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="work folder (default bench/out/multi_object, --quick: ..._quick)")
    p.add_argument("--minutes", type=float, help="T: the one model's training budget, and the six models' "
                                                 "together (default 60; --quick 0.6)")
    p.add_argument("--train-count", type=int, help="training frames (default 12000; --quick 12)")
    p.add_argument("--test-count", type=int, help="held-out frames (default 200; --quick 3)")
    p.add_argument("--size", help="held-out frame size WxH (default 640x480; --quick 160x120)")
    p.add_argument("--calib-count", type=int, help="frames the thresholds are calibrated on (default 100; "
                                                   "--quick 12)")
    p.add_argument("--workers", type=int, default=2, help="synth render processes (default 2)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads of the timing (default 2)")
    p.add_argument("--one-model-set", nargs="+", default=[], metavar="KEY=VALUE",
                   help="training overrides of the six-object model only, after the shared ones (e.g. "
                        "model.lite.stage_channels=96: wider stages, widened from the start)")
    p.add_argument("--train-scene-set", nargs="+", default=[], metavar="KEY=VALUE",
                   help="synth overrides of the training frames, after the bench's own (e.g. "
                        "'target.count=[2,4]': two to four objects per frame, as in the held-out scenes)")
    p.add_argument("--quick", action="store_true", help="tiny sizes and budget: checks every stage runs")
    args = p.parse_args(argv)
    q = args.quick
    defaults = {"minutes": 0.6 if q else 60.0, "train_count": 12 if q else 12000, "test_count": 3 if q else 200,
                "calib_count": 12 if q else 100,
                "size": "160x120" if q else "640x480",
                "out": REPO / "bench" / "out" / ("multi_object_quick" if q else "multi_object")}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.shared = shared_data_dir()
    if args.shared is None or not (args.shared / "grocery_objects").is_dir():
        p.error("the shared data (hope_ketchup/, grocery_objects/) is not found: set DOPE_HOPE_SHARED_DATA")
    return args


def per_object_recall(eval_dir: Path, method: str) -> dict[str, float]:
    """{object: recall at 2 cm} from `evaluate`'s per-object CSV of ``method`` (an object with
    no held-out instance, whose recall is empty there, left out: a --quick run's few frames)."""
    import csv

    with open(eval_dir / f"per_object_{method}.csv", newline="") as f:
        return {row["object"]: float(row["recall_2cm"]) for row in csv.DictReader(f)
                if row["row"] == "object" and row["recall_2cm"]}


def shelf_losses(out: Path, meshes: dict[str, Path], units: dict[str, str]) -> dict[str, dict[str, dict]]:
    """How each arm loses the held-out instances: {arm suffix: {breakdown label: {object:
    counts of :data:`~e2e_accuracy.LOSS_CLASSES`}}} for each of :data:`BREAKDOWNS`
    (:func:`e2e_accuracy.instance_losses`: MeanSSD with the objects' symmetries, -LS)."""
    trained = recorded_thresholds(out, "trained")

    def counts(arm: str, suffix: str, name: str, score: float | None) -> dict[str, int]:
        predictions = out / f"infer_{arm}{suffix}" / "predictions.jsonl"
        if score is None:
            score = 0.5 if trained[arm][name] is None else trained[arm][name]
        return loss_counts(instance_losses(out / "test", predictions, name, meshes[name], score, units[name]))

    return {arm: {label: {n: counts(arm, suffix, n, score) for n in OBJECTS} for label, suffix, score in BREAKDOWNS}
            for _, arm, _ in ARMS}


def recorded_thresholds(out: Path, which: str) -> dict[str, dict[str, float | None]]:
    """{arm suffix: {object: the threshold recorded with its weights, or None: none (it keeps
    infer's default)}}: ``which`` "trained" those its training run chose (OUT/run_*), "own"
    those `calibrate` chose (OUT/calibrated/)."""
    from dope_hope.model.checkpoint import load_checkpoint
    from dope_hope.model.info import ModelInfo

    def of(path: Path) -> dict[str, float | None]:
        return {o.class_name: o.min_score for o in ModelInfo.from_checkpoint(load_checkpoint(path), path).objects}

    if which == "trained":
        return {"all": of(checkpoint_of(out / "run_all")),
                "six": {n: t for name in OBJECTS for n, t in of(checkpoint_of(out / f"run_{name}")).items()}}
    return {"all": of(out / "calibrated" / "all.pt"),
            "six": {n: t for name in OBJECTS for n, t in of(out / "calibrated" / f"{name}.pt").items()}}


def losses_table(losses: dict[str, dict[str, dict]], score: str) -> str:
    """Markdown table of :func:`shelf_losses` at one breakdown (its label): per object and
    arm, the instances in each loss class."""
    classes = " / ".join(LOSS_CLASSES)
    rows = [f"| object | {ARMS[0][0]}: {classes} | {ARMS[1][0]}: {classes} |", "|---|---|---|"]
    for n in [*OBJECTS, None]:
        cells = []
        for _, arm, _ in ARMS:
            per = losses[arm][score]
            counts = per[n] if n else {k: sum(c[k] for c in per.values()) for k in LOSS_CLASSES}
            cells.append(" / ".join(str(counts[k]) for k in LOSS_CLASSES))
        rows.append(f"| {n or '**all**'} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def test_frames(folder: Path, limit: int) -> list[tuple]:
    """(rgb (H, W, 3) uint8, K (3, 3)) of the first ``limit`` held-out frames."""
    from dope_hope.io.dope_json import find_image, list_dope_frames, read_dope_json
    from dope_hope.io.images import read_rgb

    frames = []
    for path in list_dope_frames(folder)[:limit]:
        frames.append((read_rgb(find_image(path)), read_dope_json(path).K))
    return frames


def _timed_predict(predictor, rgb, K) -> tuple[float, float]:
    """(network seconds: input preparation + forward pass, decoding + PnP seconds) of
    ``predictor.predict(rgb, K)``, done in its two halves."""
    t0 = time.perf_counter()
    belief, affinity, net_in = predictor.infer_maps(rgb)
    t1 = time.perf_counter()
    predictor.detections_from_maps(belief, affinity, net_in, K)
    return t1 - t0, time.perf_counter() - t1


def time_per_frame(one: Path, singles: dict[str, Path], frames: list[tuple], threads: int,
                   warmup: int = 2) -> dict[str, float]:
    """Mean seconds per frame of the whole predictor (network, then decoding + PnP; no depth)
    of the one multi-object ONNX model, of the six one-object ONNX models in turn, and of one
    of them alone (the mean of the six), each also split into its two halves; run frame by
    frame, alternating, in this process."""
    from dope_hope.inference.predictor import DopePredictor

    all_six = DopePredictor(one, threads=threads)
    each = {name: DopePredictor(path, threads=threads) for name, path in singles.items()}
    one_times, six_times, single_times = [], [], []
    for i, (rgb, K) in enumerate(frames):
        one_t = _timed_predict(all_six, rgb, K)
        per = [_timed_predict(predictor, rgb, K) for predictor in each.values()]
        if i >= warmup:
            one_times.append(one_t)
            six_times.append(np.sum(per, axis=0))
            single_times += per
    one_m, six_m, single_m = (np.mean(t, axis=0) for t in (one_times, six_times, single_times))
    return {"one_model_s": float(one_m.sum()), "six_models_s": float(six_m.sum()),
            "one_object_model_s": float(single_m.sum()), "one_model_network_s": float(one_m[0]),
            "one_model_decode_s": float(one_m[1]), "one_object_network_s": float(single_m[0]),
            "one_object_decode_s": float(single_m[1]), "frames": len(one_times)}


def object_symmetries(meshes: dict[str, Path], units: dict[str, str]) -> dict[str, str]:
    """{object: its symmetries, where they come from and the seconds it took} as the training
    labels and MeanSSD resolve them (``dope_hope.symmetry.resolve.resolve_symmetries``)."""
    from dope_hope.symmetry.resolve import resolve_symmetries

    out = {}
    for name in OBJECTS:
        t0 = time.perf_counter()
        text = resolve_symmetries(name, meshes[name], units=units[name]).describe()
        out[name] = f"{text} [{time.perf_counter() - t0:.2f} s]"
    return out


def run_stages(args: argparse.Namespace, out: Path, meshes: dict[str, Path], units: dict[str, str]) -> CommandStages:
    """Stages 1-6 of the module docstring (each skipped when done earlier)."""
    pipe = CommandStages(out, cwd=REPO)
    names = list(OBJECTS)
    mesh_args = [str(meshes[n]) for n in names]
    unit_args = [units[n] for n in names]
    train_dir, test_dir, calib_dir = out / "train", out / "test", out / "calib"
    pipe.stage("synth-train", ["synth", "--mesh", *mesh_args, "--units", *unit_args, "--out", train_dir,
                               "--count", args.train_count, "--size", "64x64" if args.quick else "256x192",
                               "--seed", TRAIN_SEED, "--workers", args.workers, "--no-progress",
                               "--set", *TRAIN_TARGETS, *args.train_scene_set])
    options = ["--batch-size", "2", "--workers", "0"] if args.quick else []
    options += ["--set", *TRAIN_SET, *(["input.size=[64,64]", "train.threads=1"] if args.quick else [])]
    common = ["train", "--config", "lite", "--data", train_dir, "--init", "pretrained", "--resume", "--no-progress"]
    pipe.stage("train-all", [*common, "--object", *names, "--mesh", *mesh_args, "--units", *unit_args,
                             "--out", out / "run_all", "--time-budget", args.minutes, *options, *args.one_model_set])
    for n in names:
        pipe.stage(f"train-{n}", [*common, "--object", n, "--mesh", meshes[n], "--units", units[n],
                                  "--out", out / f"run_{n}", "--time-budget", args.minutes / 6, *options])
    for stage, folder, count, seed in (("synth-test", test_dir, args.test_count, TEST_SEED),
                                       ("synth-calib", calib_dir, args.calib_count, CALIB_SEED)):
        pipe.stage(stage, ["synth", "--mesh", *mesh_args, "--units", *unit_args, "--out", folder,
                           "--count", count, "--size", args.size, "--seed", seed,
                           "--workers", args.workers, "--depth-noise", "--no-progress",
                           "--backgrounds", args.shared / "backgrounds", "--set", *TEST_SCENE])
    one_ckpt = checkpoint_of(out / "run_all")
    single_ckpts = {n: checkpoint_of(out / f"run_{n}") for n in names}

    def mesh_flags(objects: list[str]) -> list[str]:
        return [a for n in objects for a in ("--mesh", f"{n}={meshes[n]}", "--mesh-units", f"{n}={units[n]}")]

    def infer(folder: Path, *flags) -> list:  # --fast: -LS, or with --icp -LS + ICP (not the still-image default)
        return ["infer", folder, "--fast", "--depth", "auto", *flags, "--no-overlay", "--no-progress", *mesh_flags(names)]

    six = [a for n in names for a in ("--weights", single_ckpts[n])]
    for stage, folder, flags in (("infer-{}", test_dir, ()), ("infer-calib-{}", calib_dir, ()),
                                 ("infer-{}-icp", test_dir, ("--icp",))):
        for arm, weights in (("all", ["--weights", one_ckpt]), ("six", six)):
            name = stage.format(arm)  # its output folder: the name with underscores
            pipe.stage(name, [*infer(folder, "--min-score", "0", *flags), *weights, "--out", out / name.replace("-", "_")])
    calibrated = {"all": out / "calibrated" / "all.pt", **{n: out / "calibrated" / f"{n}.pt" for n in names}}
    for key, weights, arm, objects in (("all", one_ckpt, "all", names),
                                       *((n, single_ckpts[n], "six", [n]) for n in names)):
        pipe.stage(f"calibrate-{key}", ["calibrate", "-p", out / f"infer_calib_{arm}" / "predictions.jsonl",
                                        "-d", calib_dir, "--weights", weights, "--out", calibrated[key],
                                        "--no-progress", *mesh_flags(objects)])
    pipe.stage("infer-all-own", [*infer(test_dir), "--weights", calibrated["all"], "--out", out / "infer_all_own"])
    pipe.stage("infer-six-own", [*infer(test_dir), *(a for n in names for a in ("--weights", calibrated[n])),
                                 "--out", out / "infer_six_own"])
    evaluate = ["evaluate", "-d", test_dir, "--metric", "meanssd", "--no-bop-ar", "--no-progress", *mesh_flags(names)]
    for _, arm, method in ARMS:
        for suffix, tag in (("", ""), ("_icp", "-ICP")):
            pipe.stage(f"eval-{arm}{suffix.replace('_', '-')}", [
                *evaluate, "-p", out / f"infer_{arm}{suffix}" / "predictions.jsonl", "--method", method + tag,
                "--out", out / f"eval_{arm}{suffix}"])
    pipe.stage("export-all", ["export", "--weights", one_ckpt, "--out", out / "onnx" / "all.onnx"])
    for n in names:
        pipe.stage(f"export-{n}", ["export", "--weights", single_ckpts[n], "--out", out / "onnx" / f"{n}.onnx"])
    return pipe


def report(args: argparse.Namespace, out: Path, pipe: CommandStages, symmetries: dict[str, str],
           meshes: dict[str, Path], units: dict[str, str]) -> dict:
    """The recall table, the steps trained and the timing (text printed and written to
    OUT/results.md); returns the figures for OUT/results.json."""
    names = list(OBJECTS)
    recall_one, recall_six = (per_object_recall(out / f"eval_{arm}", method) for _, arm, method in ARMS)
    icp_one, icp_six = (per_object_recall(out / f"eval_{arm}_icp", method + "-ICP") for _, arm, method in ARMS)
    losses = shelf_losses(out, meshes, units)
    breakdown = "\n\n".join(f"At {label}:\n\n{losses_table(losses, label)}" for label in losses["all"])
    own, trained_own = recorded_thresholds(out, "own"), recorded_thresholds(out, "trained")

    def listed(chosen: dict[str, dict[str, float | None]]) -> str:
        return "; ".join(f"{label}: " + ", ".join(f"{n} {'none (0.5)' if chosen[arm][n] is None else chosen[arm][n]}"
                                                  for n in names) for label, arm, _ in ARMS)

    thresholds = ("Each object's threshold its training run chose (F1 at 10 cm MeanSSD on its validation frames): "
                  f"{listed(trained_own)}\n\nEach object's own threshold (`dope-hope calibrate`, F1 at 10 cm "
                  f"MeanSSD on {args.calib_count} other frames, seed {CALIB_SEED}): {listed(own)}")
    mean_one, mean_six, mean_icp_one, mean_icp_six = (statistics.mean(r.get(n, 0.0) for n in names)
                                                      for r in (recall_one, recall_six, icp_one, icp_six))
    steps = {run: json.loads((out / run / "summary.json").read_text())["step"]
             for run in ["run_all", *(f"run_{n}" for n in names)]}
    timing = time_per_frame(out / "onnx" / "all.onnx", {n: out / "onnx" / f"{n}.onnx" for n in names},
                            test_frames(out / "test", args.test_count if args.quick else min(args.test_count, 52)),
                            args.threads)
    rows = ["| object | one six-object model | six one-object models | one model, -LS + ICP | six models, -LS + ICP |",
            "|---|---|---|---|---|"]
    rows += [f"| {n} | {percent_text(recall_one.get(n))} | {percent_text(recall_six.get(n))} | "
             f"{percent_text(icp_one.get(n))} | {percent_text(icp_six.get(n))} |" for n in names]
    rows.append(f"| **mean** | **{percent_text(mean_one)}** | **{percent_text(mean_six)}** | "
                f"**{percent_text(mean_icp_one)}** | **{percent_text(mean_icp_six)}** |")
    table = "\n".join(rows)
    ratio_single = timing["one_model_s"] / timing["one_object_model_s"]
    ratio_six = timing["six_models_s"] / timing["one_model_s"]
    ms = {k: 1000 * v for k, v in timing.items() if k.endswith("_s")}
    speed = (f"time per {args.size} frame (onnxruntime, {args.threads} threads; network, then decoding + PnP; "
             f"{timing['frames']} frames): one model {ms['one_model_s']:.1f} ms ({ms['one_model_network_s']:.1f} + "
             f"{ms['one_model_decode_s']:.1f}; {1 / timing['one_model_s']:.1f} frames/s), a one-object model "
             f"{ms['one_object_model_s']:.1f} ms ({ms['one_object_network_s']:.1f} + {ms['one_object_decode_s']:.1f}), "
             f"the six {ms['six_models_s']:.1f} ms; one model / one-object model = {ratio_single:.2f}x (network "
             f"{timing['one_model_network_s'] / timing['one_object_network_s']:.2f}x), six models / one model = "
             f"{ratio_six:.2f}x")
    trained = (f"steps: one model {steps['run_all']} in {args.minutes:g} min; one-object models "
               + ", ".join(f"{n} {steps[f'run_{n}']}" for n in names) + f" in {args.minutes / 6:g} min each")
    times = ", ".join(f"{k} {v:.0f} s" for k, v in pipe.timings.items())
    (out / "results.md").write_text(
        f"# Multi-object benchmark: T = {args.minutes:g} min\n\n{cpu_line()}\n\n"
        f"Recall at 2 cm MeanSSD with -LS, and with -LS + ICP ({args.test_count} held-out frames at {args.size}, "
        f"two to four objects each, photo background; every detection, ranked by score):\n\n{table}\n\n"
        "Symmetries (training labels and MeanSSD):\n\n" + "".join(f"- {n}: {t}\n" for n, t in symmetries.items())
        + "\nWhere the held-out instances are lost (MeanSSD with those symmetries, -LS; instances per object: "
        + ", ".join(LOSS_CLASSES) + f"):\n\n{breakdown}\n\n{thresholds}\n\n{trained}\n\n"
        f"{speed}\n\nStage times: {times}\n")
    print(f"\n{table}\n\n{breakdown}\n\n{thresholds}\n\n{trained}\n{speed}\nstage times: {times}\n"
          f"written: {out / 'results.md'}, {out / 'results.json'}")
    return {"recall_2cm_one_model": recall_one, "recall_2cm_six_models": recall_six, "mean_one_model": mean_one,
            "mean_six_models": mean_six, "recall_2cm_icp_one_model": icp_one, "recall_2cm_icp_six_models": icp_six,
            "mean_icp_one_model": mean_icp_one, "mean_icp_six_models": mean_icp_six, "lost": losses,
            "own_thresholds": own, "trained_thresholds": trained_own, "steps": steps, "timing": timing,
            "stage_seconds": pipe.timings, "symmetries": symmetries}


def optional_settings(args: argparse.Namespace) -> dict:
    """The settings entries of ``--one-model-set`` and ``--train-scene-set`` (none when not
    given: a folder of a run without them stays valid)."""
    given = {"one_model_set": args.one_model_set, "train_scene_set": args.train_scene_set}
    return {key: value for key, value in given.items() if value}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out: Path = args.out.resolve()
    meshes = {name: (args.shared / rel).resolve() for name, (rel, _) in OBJECTS.items()}
    units = {name: u for name, (_, u) in OBJECTS.items()}
    settings = {"objects": {n: str(p) for n, p in meshes.items()}, "minutes": args.minutes,
                "train_count": args.train_count, "test_count": args.test_count, "size": args.size,
                "calib_count": args.calib_count, "calib_seed": CALIB_SEED,
                "train_targets": TRAIN_TARGETS, "train_set": TRAIN_SET, **optional_settings(args),
                "test_scene": TEST_SCENE, "quick": args.quick, "train_seed": TRAIN_SEED, "test_seed": TEST_SEED}
    check_settings(out, settings)
    print(cpu_line(), flush=True)
    print(f"multi-object: {', '.join(OBJECTS)}; {args.train_count} training frames; one lite model "
          f"{args.minutes:g} min vs six {args.minutes / 6:g} min each; {args.test_count} test frames at "
          f"{args.size}; {os.cpu_count()} CPU core(s){' [--quick: numbers are meaningless]' if args.quick else ''}; "
          f"work folder {out}", flush=True)
    symmetries = object_symmetries(meshes, units)
    for name, text in symmetries.items():
        print(f"symmetries: {name}: {text}", flush=True)
    pipe = run_stages(args, out, meshes, units)
    figures = report(args, out, pipe, symmetries, meshes, units)
    (out / "results.json").write_text(json.dumps({"settings": settings, "cpu": cpu_description(), **figures},
                                                 indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
