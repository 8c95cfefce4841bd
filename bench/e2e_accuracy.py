"""End-to-end accuracy of the whole pipeline on a real HOPE mesh (Ketchup), with the real CLI.

Stages (each one a `dope-hope` command run as a subprocess, exactly what a user types; the
commands are printed and logged to OUT/logs/):

1. ``synth-train``: `dope-hope synth` a training set for the mesh (seed 1), rendered at the
   lite input size (256x192: no resampling in training). ``--recipe defaults`` (the default):
   the packaged configs/synth.yaml as a user gets it (clutter backgrounds, look-alikes, sensor
   artefacts, empty frames); ``--recipe plain``: those switched off (the frames of the earlier
   figures in bench/RESULTS.md). No training frame uses a photograph unless
   ``--train-backgrounds DIR`` gives some (`dope-hope synth --backgrounds`; never the test
   set's photographs: a file of the test set's folder among them is refused).
2. ``train``: `dope-hope train --config lite` for a fixed wall-clock budget (default 20
   minutes on the 2 CPU cores; `--train-minutes`), validation on the config's seeded split
   (lite: `train.val_fraction` 0.025, 300 of the 12,000 frames), with
   symmetry-aware labels (`--train-set`, default ``targets.symmetry=auto``); from scratch, or
   with `--init` from the shipped pretrained start, the demo model or a checkpoint's weights.
3. ``synth-test``: a held-out test set at 640x480 (the RealSense colour size) with other seeds
   (1001), photo backgrounds (`--backgrounds`) and RealSense-like depth noise (`--depth-noise`).

Both sets share the target ranges of :data:`TARGET` (one or two instances at 0.45-1.0 m, as
in the HOPE scenes' table-top views) over configs/synth.yaml's distractors, occluders and
lights; the test set is the same for both recipes (:data:`SCENE`: plain, photo backgrounds).
4. ``infer-ls`` / ``infer`` / ``infer-icp`` / ``infer-turns`` / ``infer-scales``: `dope-hope
   infer TEST --depth auto` (with the depth line search, "-LS"), the same without `--depth` (no
   -LS), with `--depth auto --icp` (-LS, then ICP against the depth: rotation too), with
   `--depth auto --set appearance.trained_turns=true` (each pose turned about the bottle's axis
   where its textured render says so, then -LS: ``dope_hope.inference.turns``), and with
   `--depth auto --set multiscale.scales=[...]` (:data:`SCALES`: the network at three working
   sizes, the detections pooled, then -LS: ``dope_hope.inference.scales``), with the mesh for
   the points (each with ``--fast``: the packaged defaults with that one change); ``infer-default``:
   `dope-hope infer TEST --depth auto`, the still-image default (the accurate preset: three
   working sizes, ICP where there is depth and a mesh, the turns where not).
5. ``eval-meanssd`` / ``eval-addh``: `dope-hope evaluate` of the prediction files: recall at
   2 cm and 10 cm and the median error of the true positives (at 10 cm) for MeanSSD and ADD-H
   (500 model points, the bottle category's symmetries), and the BOP19 AR_MSSD / AR_MSPD /
   AR_VSD, over every annotated instance (HOPE's convention, `evaluate`'s default);
   ``eval-bop19``: MeanSSD recall over BOP19's targets only (`--min-visible bop19`: instances
   at least a tenth visible).

Prints the CPU and its precision flags (:func:`dope_hope.devices.cpu_line`), the steps trained
and the share of the time budget used, the table, and how the held-out instances are lost
(with -LS, detections scoring at least what `infer` keeps by default, the threshold the run
recorded (:func:`recorded_threshold`): none, beyond 10 cm, within 10 cm
but not 2 cm, within 2 cm MeanSSD; in all, then per band of the visible fraction: below 0.1 an
instance is no BOP19 target); writes OUT/results.md + OUT/results.json. Resumable at stage
granularity: a stage whose marker OUT/stages/<stage>.json exists is skipped (an interrupted
synth resumes frame by frame, an interrupted train with --resume); OUT/e2e_settings.json
refuses a rerun with other settings in the same folder.

    python bench/e2e_accuracy.py                                   # 2 CPU cores, ~37 min
    python bench/e2e_accuracy.py --quick --out /tmp/e2e_quick      # tiny, < 1 min: checks the plumbing
    python bench/e2e_accuracy.py --train-set targets.symmetry=none --out runs/e2e_plain  # official labels
    python bench/e2e_accuracy.py --train-minutes 30 --init demo --out runs/e2e_init      # from the demo model
    python bench/e2e_accuracy.py --train-minutes 30 --init pretrained --out runs/e2e_pre  # the pretrained start
    python bench/e2e_accuracy.py --train-minutes 30 --init pretrained --recipe plain --out runs/e2e_plain
    python bench/e2e_accuracy.py --train-minutes 30 --init pretrained --train-backgrounds photos \
        --out runs/e2e_photos              # training frames over photographs (bench/training_photos.py)
    python bench/e2e_accuracy.py --config dope_dr_50 --train-minutes 240 --train-count 20000 \\
        --workers 8 --device cuda --out bench/out/e2e_dr50         # on a GPU machine

The mesh defaults to $DOPE_HOPE_SHARED_DATA/hope_ketchup/textured.obj, else
../shared/data/hope_ketchup/textured.obj next to the repository (never copied into it);
the backgrounds to the `backgrounds/` folder beside it.
"""
from __future__ import annotations

import argparse
import filecmp
import json
import math
import os
import sys
from pathlib import Path

from dope_hope.devices import cpu_description, cpu_line
from dope_hope.evaluation.matching import VISIBLE_FLOORS
from dope_hope.evaluation.thresholds import thresholds_in_use
from dope_hope.model.checkpoint import load_checkpoint
from dope_hope.model.info import ModelInfo
from dope_hope.staged_run import CommandStages, settings_changed
from dope_hope.synth.settings import PLAIN_OVERRIDES

REPO = Path(__file__).resolve().parent.parent
#: Synth seeds: training and held-out test frames never share a (seed, index) pair.
TRAIN_SEED, TEST_SEED = 1, 1001


def set_args(overrides: dict, prefix: str = "") -> list[str]:
    """Nested overrides -> `--set` arguments ("section.key=value")."""
    out = []
    for key, value in overrides.items():
        if isinstance(value, dict):
            out += set_args(value, f"{prefix}{key}.")
        else:
            out.append(f"{prefix}{key}={json.dumps(value)}")
    return out


#: Target ranges of both sets (`dope-hope synth --set`), over configs/synth.yaml.
TARGET = ["target.count=[1,2]", "target.distance_m=[0.45,1.0]"]
#: The test set's scene, and the training set's with ``--recipe plain``: without the clutter
#: backgrounds, hard negatives and sensor artefacts of configs/synth.yaml (the frames of the
#: "plain" row of bench/RESULTS.md "End-to-end accuracy (HOPE Ketchup)": same seeds, same frames).
SCENE = [*TARGET, *set_args(PLAIN_OVERRIDES)]
#: The training set's scene per ``--recipe``.
RECIPES = {"defaults": TARGET, "plain": SCENE}
#: The loss classes of a held-out instance (:func:`instance_losses`).
LOSS_CLASSES = ("no detection", "beyond 10 cm", "within 10 cm, not 2 cm", "within 2 cm")
#: BOP19's visible-fraction floor of its targets (`dope-hope evaluate --min-visible bop19`).
BOP_VISIBLE_FLOOR = VISIBLE_FLOORS["bop19"]
#: Visible-fraction bands of the breakdown: (label, low, high); below 0.1 an instance is not a
#: BOP19 target (bop_toolkit's visib_gt_min), nearly all of it hidden or outside the image.
VISIBILITY_BANDS = (("< 0.1", 0.0, 0.1), ("0.1-0.5", 0.1, 0.5), ("0.5-0.95", 0.5, 0.95), (">= 0.95", 0.95, math.inf))
#: Training overrides: symmetry-aware labels for the bottle (6x the recall at 2 cm ADD-H of the
#: official labels in the same 20 minutes; bench/RESULTS.md).
TRAIN_SET = ("targets.symmetry=auto",)
#: The ``infer-scales`` stage's working sizes (``multiscale.scales``): the model's own, and 0.75
#: and 1.33 of it (on the six-object bench's T = 10 model these three lost the fewest
#: instances of the pairs and triples tried with 0.625-1.33).
SCALES = "multiscale.scales=[1,0.75,1.33]"


def shared_data_dir() -> Path | None:
    """$DOPE_HOPE_SHARED_DATA, else ../shared/data beside the repository (None if absent)."""
    env = os.environ.get("DOPE_HOPE_SHARED_DATA")
    for c in ([Path(env)] if env else []) + [REPO.parent / "shared" / "data", REPO / "shared" / "data"]:
        if (c / "hope_ketchup" / "textured.obj").is_file():
            return c
    return None


def default_mesh(parser: argparse.ArgumentParser, mesh: Path | None) -> Path:
    """``mesh``, else the shared HOPE Ketchup mesh (a parser error when there is none)."""
    if mesh is not None:
        return mesh
    shared = shared_data_dir()
    if shared is None:
        parser.error("no --mesh and no shared data (set DOPE_HOPE_SHARED_DATA or pass --mesh)")
    return shared / "hope_ketchup" / "textured.obj"


def shared_defaults(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``args.mesh`` / ``args.backgrounds`` when not given: the shared HOPE Ketchup mesh and
    background photos (a parser error when no mesh is at hand)."""
    shared = shared_data_dir()
    args.mesh = default_mesh(parser, args.mesh)
    if args.backgrounds is None and shared is not None and (shared / "backgrounds").is_dir():
        args.backgrounds = shared / "backgrounds"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="work folder (default bench/out/e2e, --quick: bench/out/e2e_quick)")
    p.add_argument("--mesh", type=Path, help="object mesh (default: the shared HOPE Ketchup textured.obj)")
    p.add_argument("--object", default="Ketchup", help="class name (default Ketchup)")
    p.add_argument("--backgrounds", type=Path, help="background photos of the test set "
                                                    "(default: the shared data's backgrounds/)")
    p.add_argument("--train-backgrounds", type=Path, metavar="DIR",
                   help="photographs behind the training frames (`dope-hope synth --backgrounds`; default "
                        "none: the recipe's procedural backgrounds); none of the test set's photographs")
    p.add_argument("--config", default="lite", help="training config (lite; dope_dr_50 on a GPU)")
    p.add_argument("--train-minutes", type=float, help="training wall-clock budget (default 20; --quick 0.2)")
    p.add_argument("--train-count", type=int, help="training frames (default 12000; --quick 8)")
    p.add_argument("--train-size", help="training frame size WxH (default 256x192, the lite input; --quick 64x64)")
    p.add_argument("--test-count", type=int, help="test frames (default 200; --quick 3)")
    p.add_argument("--size", help="test frame size WxH (default 640x480; --quick 160x120)")
    p.add_argument("--workers", type=int, default=2, help="synth render processes (default 2)")
    p.add_argument("--device", help="torch device for train and infer (default: train auto, infer cpu)")
    p.add_argument("--train-set", nargs="+", default=list(TRAIN_SET), metavar="KEY=VALUE",
                   help="training config overrides (`dope-hope train --set`; default "
                        f"{' '.join(TRAIN_SET)}; targets.symmetry=none gives the official labels)")
    p.add_argument("--init", metavar="pretrained|demo|none|PATH",
                   help="the weights training starts from (`dope-hope train --init`): 'pretrained' the "
                        "shipped pretrained lite start, 'demo' the shipped demo model, a checkpoint PATH; "
                        "default none (a random start, as the script-default row of bench/RESULTS.md "
                        "'End-to-end accuracy')")
    p.add_argument("--recipe", choices=sorted(RECIPES), default="defaults",
                   help="training frames: 'defaults' the packaged configs/synth.yaml (clutter, look-alikes, "
                        "sensor artefacts, empty frames; what a user trains on), 'plain' those switched off "
                        "(the earlier figures' frames); the held-out test set is the same for both")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes and budget: checks that every stage runs (numbers meaningless)")
    args = p.parse_args(argv)
    q = args.quick
    defaults = {"train_minutes": 0.2 if q else 20.0, "train_count": 8 if q else 12000,
                "train_size": "64x64" if q else "256x192",
                "test_count": 3 if q else 200, "size": "160x120" if q else "640x480",
                "out": REPO / "bench" / "out" / ("e2e_quick" if q else "e2e")}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    shared_defaults(p, args)
    if not args.mesh.is_file():
        p.error(f"{args.mesh}: mesh not found")
    if args.train_backgrounds is not None:
        if not args.train_backgrounds.is_dir():
            p.error(f"--train-backgrounds {args.train_backgrounds}: not a folder")
        shared_photo = test_photo_among(args.train_backgrounds, args.backgrounds)
        if shared_photo is not None:
            p.error(f"--train-backgrounds {args.train_backgrounds}: {shared_photo.name} is a photograph "
                    "of the test set (--backgrounds): train on other photographs")
    return args


def test_photo_among(train_dir: Path, test_dir: Path | None) -> Path | None:
    """A file of the folder ``train_dir`` whose bytes equal a file of ``test_dir`` (None: none;
    ``filecmp.cmp`` compares the sizes before the bytes)."""
    if test_dir is None or not test_dir.is_dir():
        return None
    test = [f for f in test_dir.iterdir() if f.is_file()]
    for f in sorted(train_dir.iterdir()):
        if f.is_file() and any(filecmp.cmp(f, twin, shallow=False) for twin in test):
            return f
    return None


def check_settings(out: Path, settings: dict) -> None:
    """Record the run's settings; refuse to mix stages made with other settings."""
    diff = settings_changed(out / "e2e_settings.json", settings)
    if diff:
        raise SystemExit(f"{out} holds a run with other settings ({', '.join(diff)}); "
                         "use another --out or delete it")


def checkpoint_of(run_dir: Path) -> Path:
    """best.pt (best validation keypoint accuracy) if the run wrote one, else last.pt."""
    for name in ("best.pt", "last.pt"):
        if (run_dir / name).is_file():
            return run_dir / name
    raise SystemExit(f"{run_dir}: no checkpoint (best.pt / last.pt) after training")


def percent_text(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f} %"


def number_text(v, digits: int = 2) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def results_table(out: Path, methods: dict[str, str]) -> tuple[str, dict]:
    """Markdown table from the evaluate summaries; ``methods``: "MODEL REFINEMENT" label ->
    evaluate method name. Recall over every annotated instance (HOPE's convention), and at 2
    and 10 cm MeanSSD over BOP19's targets ("BOP")."""
    ms = json.loads((out / "eval_meanssd" / "summary.json").read_text())
    ah = json.loads((out / "eval_addh" / "summary.json").read_text())
    bop = json.loads((out / "eval_bop19" / "summary.json").read_text())
    rows, data = [], {}
    header = ("| method | depth refinement | recall 2 cm MeanSSD | recall 10 cm MeanSSD | median MeanSSD (cm) | "
              "recall 2 cm ADD-H | recall 10 cm ADD-H | median ADD-H (cm) | AR_MSSD | AR_MSPD | AR_VSD | "
              "BOP targets: recall 2 cm MeanSSD | BOP targets: recall 10 cm MeanSSD |")
    rows.append(header)
    rows.append("|" + "|".join(["---"] * (header.count("|") - 1)) + "|")
    for label, name in methods.items():
        m = ms["methods"][name]
        a = ah["methods"][name]
        mo, ao, ar = m["overall"] or {}, a["overall"] or {}, m.get("bop19") or {}
        bo = bop["methods"][name]["overall"] or {}
        rec = {"recall_2cm_meanssd": mo.get("recall_2cm"), "recall_10cm_meanssd": mo.get("recall_10cm"),
               "median_meanssd_cm": mo.get("median_tp_error_cm"),
               "recall_2cm_addh": ao.get("recall_2cm"), "recall_10cm_addh": ao.get("recall_10cm"),
               "median_addh_cm": ao.get("median_tp_error_cm"),
               "ar_mssd": ar.get("ar_mssd"), "ar_mspd": ar.get("ar_mspd"), "ar_vsd": ar.get("ar_vsd"),
               "recall_2cm_meanssd_bop_targets": bo.get("recall_2cm"),
               "recall_10cm_meanssd_bop_targets": bo.get("recall_10cm"), "detections": m["detections"]}
        data[label] = rec
        method, ls = label.rsplit(" ", 1)
        rows.append(f"| {method} | {ls} | {percent_text(rec['recall_2cm_meanssd'])} | {percent_text(rec['recall_10cm_meanssd'])} | "
                    f"{number_text(rec['median_meanssd_cm'])} | {percent_text(rec['recall_2cm_addh'])} | "
                    f"{percent_text(rec['recall_10cm_addh'])} | {number_text(rec['median_addh_cm'])} | "
                    f"{number_text(rec['ar_mssd'], 3)} | {number_text(rec['ar_mspd'], 3)} | {number_text(rec['ar_vsd'], 3)} | "
                    f"{percent_text(rec['recall_2cm_meanssd_bop_targets'])} | "
                    f"{percent_text(rec['recall_10cm_meanssd_bop_targets'])} |")
    return "\n".join(rows), data


def instance_losses(test_dir: Path, predictions: Path, object_name: str, mesh: Path,
                    min_score: float, mesh_units: str | None = None) -> list[tuple[float, str]]:
    """How each held-out GT instance of ``object_name`` is lost: the estimate (score >=
    ``min_score``) paired with it as `evaluate` pairs them at 2 cm MeanSSD, then the remaining
    ones without a threshold (:func:`dope_hope.evaluation.matching.match_frame`), and its
    MeanSSD error (the mesh in ``mesh_units``, None: by its suffix; the object's symmetries as
    `evaluate` resolves them). Returns (visible fraction, one of :data:`LOSS_CLASSES`) per
    instance (a missing visibility counts as 1, as the BOP19 targets count it)."""
    from dope_hope.evaluation.datasets import assign_predictions, load_dataset
    from dope_hope.evaluation.evaluate import cuboid_centres_to_origins
    from dope_hope.evaluation.matching import match_frame
    from dope_hope.evaluation.object_models import load_models
    from dope_hope.io.predictions import read_predictions

    dataset = load_dataset(test_dir)
    models = load_models([object_name], [f"{object_name}={mesh}"], mesh_units=mesh_units,
                         recorded_sizes=dataset.cuboid_sizes)  # as evaluate loads it
    preds = [p for p in read_predictions(predictions)[0] if p.class_name == object_name and p.score >= min_score]
    cuboid_centres_to_origins(preds, models)
    out = []
    for frame, estimates in zip(dataset.frames, assign_predictions(dataset, preds)[0]):
        gts = [o for o in frame.objects if o.class_name == object_name]
        if not gts:
            continue
        match = match_frame(estimates, gts, models[object_name], metric="meanssd")
        for g, p in enumerate(match.estimate_of_gt):
            error = math.inf if p < 0 else float(match.errors[p, g])
            key = (LOSS_CLASSES[0] if p < 0 else LOSS_CLASSES[1] if error >= 0.10
                   else LOSS_CLASSES[2] if error >= 0.02 else LOSS_CLASSES[3])
            visibility = 1.0 if gts[g].visibility is None else float(gts[g].visibility)
            out.append((visibility, key))
    return out


def bop_targets(losses: list[tuple[float, str]]) -> list[tuple[float, str]]:
    """The instances of :func:`instance_losses` that are BOP19 targets (visible >= 0.1)."""
    return [x for x in losses if x[0] >= BOP_VISIBLE_FLOOR]


def loss_counts(losses: list[tuple[float, str]]) -> dict[str, int]:
    """Counts of :data:`LOSS_CLASSES` over :func:`instance_losses`' instances."""
    counts = dict.fromkeys(LOSS_CLASSES, 0)
    for _, key in losses:
        counts[key] += 1
    return counts


def losses_by_visibility(losses: list[tuple[float, str]]) -> dict[str, dict[str, int]]:
    """:func:`loss_counts` per band of :data:`VISIBILITY_BANDS` (label -> counts)."""
    return {label: loss_counts([x for x in losses if lo <= x[0] < hi]) for label, lo, hi in VISIBILITY_BANDS}


def recorded_threshold(weights: Path, object_name: str) -> float:
    """The score threshold `infer` runs ``object_name`` of ``weights`` at: the one its training
    run chose and recorded, else the model's own, else configs/infer.yaml's."""
    info = ModelInfo.from_checkpoint(load_checkpoint(weights), weights)
    return thresholds_in_use(info.objects, info.min_score)[object_name]


def breakdown_text(counts: dict[str, int], min_score: float) -> str:
    total = max(1, sum(counts.values()))
    return (f"held-out instances ({sum(counts.values())}, scores >= {min_score:g}, MeanSSD): "
            + ", ".join(f"{k} {v} ({100 * v / total:.1f} %)" for k, v in counts.items()))


def visibility_text(bands: dict[str, dict[str, int]]) -> str:
    """One line per visibility band: its instances and their loss classes."""
    return "\n".join(f"  visible {label}: {sum(c.values())} instances: "
                     + ", ".join(f"{k} {v}" for k, v in c.items()) for label, c in bands.items())


def run_stages(args: argparse.Namespace, out: Path, settings: dict) -> tuple[CommandStages, Path, dict, str, dict]:
    """Stages 1-5 of the module docstring (each skipped when done earlier); returns the
    pipeline, the checkpoint, the run's summary, its steps-and-budget line and the methods
    ("MODEL REFINEMENT" label -> evaluate method name)."""
    pipe = CommandStages(out, cwd=REPO)
    mesh = args.mesh.resolve()
    train_dir, test_dir, run_dir = out / "train", out / "test", out / "run"
    common = ["--mesh", mesh, "--class-name", args.object, "--no-progress"]
    photos = [] if args.train_backgrounds is None else ["--backgrounds", args.train_backgrounds.resolve()]
    pipe.stage("synth-train", ["synth", *common, "--set", *RECIPES[args.recipe], "--size", args.train_size,
                               "--out", train_dir, "--count", args.train_count, "--seed", TRAIN_SEED,
                               "--workers", args.workers, *photos])
    train = ["train", "--config", args.config, "--data", train_dir, "--object", args.object,
             "--mesh", mesh, "--out", run_dir, "--time-budget", args.train_minutes, "--resume", "--no-progress"]
    if args.device:
        train += ["--device", args.device]
    train += ["--init", settings.get("init", "none")]
    sets = list(args.train_set)
    if args.quick:  # a tiny-input run for the small budget: checks the plumbing only
        train += ["--batch-size", "2", "--workers", "0"]
        sets += ["input.size=[64,64]", "train.threads=1"]
    if sets:
        train += ["--set", *sets]
    pipe.stage("train", train)
    ckpt = checkpoint_of(run_dir)
    trained = json.loads((run_dir / "summary.json").read_text())
    share = trained["budget_used_s"] / (60.0 * args.train_minutes)
    trained_text = (f"trained {trained['step']} steps ({trained['status']}), {trained['budget_used_s']:.0f} s: "
                    f"{100 * share:.1f} % of the {args.train_minutes:g}-min budget")
    print(trained_text, flush=True)
    test = ["synth", *common, "--set", *SCENE, "--size", args.size, "--out", test_dir, "--count", args.test_count, "--seed", TEST_SEED,
            "--workers", args.workers, "--depth-noise"]
    if args.backgrounds is not None:
        test += ["--backgrounds", args.backgrounds.resolve()]
    pipe.stage("synth-test", test)
    # --min-score 0: every detection, ranked by score, as the figures in bench/RESULTS.md were
    # measured (infer's default drops scores under the threshold the run recorded, else 0.5).
    infer = ["infer", test_dir, "--weights", ckpt, "--mesh", mesh, "--no-overlay", "--no-progress",
             "--min-score", "0"]
    if args.device:
        infer += ["--device", args.device]
    fast = [*infer, "--fast"]  # each method on the packaged defaults, one setting changed
    pipe.stage("infer-ls", fast + ["--depth", "auto", "--out", out / "infer_ls"])
    pipe.stage("infer", fast + ["--out", out / "infer"])
    name = Path(args.config).stem.replace("_", "-")
    methods = {f"{name} -LS": f"{name}-LS", f"{name} none": name, f"{name} -LS+ICP": f"{name}-LS-ICP",
               f"{name} turns+-LS": f"{name}-turns-LS", f"{name} scales+-LS": f"{name}-scales-LS",
               f"{name} default": f"{name}-default"}
    pipe.stage("infer-icp", fast + ["--depth", "auto", "--icp", "--out", out / "infer_icp"])
    pipe.stage("infer-turns", fast + ["--depth", "auto", "--set", "appearance.trained_turns=true",
                                      "--out", out / "infer_turns"])
    pipe.stage("infer-scales", fast + ["--depth", "auto", "--set", SCALES, "--out", out / "infer_scales"])
    pipe.stage("infer-default", infer + ["--depth", "auto", "--out", out / "infer_default"])  # an image's preset
    evaluate = ["evaluate", "-p", out / "infer_ls" / "predictions.jsonl", out / "infer" / "predictions.jsonl",
                out / "infer_icp" / "predictions.jsonl", out / "infer_turns" / "predictions.jsonl",
                out / "infer_scales" / "predictions.jsonl", out / "infer_default" / "predictions.jsonl",
                "--method", *methods.values(), "-d", test_dir,
                "--mesh", f"{args.object}={mesh}", "--no-progress"]
    pipe.stage("eval-meanssd", evaluate + ["--metric", "meanssd,addh", "--bop-ar", "--out", out / "eval_meanssd"])
    pipe.stage("eval-addh", evaluate + ["--metric", "addh,meanssd", "--no-bop-ar", "--out", out / "eval_addh"])
    pipe.stage("eval-bop19", evaluate + ["--metric", "meanssd", "--no-bop-ar", "--min-visible", "bop19",
                                         "--out", out / "eval_bop19"])
    return pipe, ckpt, trained, trained_text, methods


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out: Path = args.out.resolve()
    settings = {"mesh": str(args.mesh.resolve()), "object": args.object, "config": args.config,
                "train_minutes": args.train_minutes, "train_count": args.train_count,
                "train_size": args.train_size, "train_set": list(args.train_set), "scene": SCENE,
                "test_count": args.test_count, "size": args.size, "device": args.device,
                "backgrounds": None if args.backgrounds is None else str(args.backgrounds.resolve()),
                "quick": args.quick, "train_seed": TRAIN_SEED, "test_seed": TEST_SEED}
    if args.recipe != "plain":  # only when not plain: earlier runs' settings stay valid
        settings["recipe"] = args.recipe
    if args.train_backgrounds is not None:  # only when given: earlier runs' settings stay valid
        settings["train_backgrounds"] = str(args.train_backgrounds.resolve())
    if args.init is not None and args.init != "none":  # only when given: earlier runs' settings stay valid
        settings["init"] = args.init if args.init in ("pretrained", "demo") else str(Path(args.init).resolve())
    check_settings(out, settings)
    print(cpu_line(), flush=True)
    print(f"e2e accuracy: {args.object} ({args.mesh}), {args.train_count} training frames ({args.recipe} recipe), "
          f"{args.config} for {args.train_minutes:g} min, {args.test_count} test frames at {args.size}, "
          f"{os.cpu_count()} CPU core(s){' [--quick: numbers are meaningless]' if args.quick else ''}; "
          f"work folder {out}", flush=True)
    pipe, ckpt, trained, trained_text, methods = run_stages(args, out, settings)
    mesh, test_dir = args.mesh.resolve(), out / "test"
    share = trained["budget_used_s"] / (60.0 * args.train_minutes)
    table, data = results_table(out, methods)
    min_score = recorded_threshold(ckpt, args.object)  # what a user's `infer` keeps
    breakdowns, lost_text = {}, []
    for label, folder in (("-LS", "infer_ls"), (f"three working sizes ({SCALES})", "infer_scales"),
                          ("the still-image default (the accurate preset)", "infer_default")):
        losses = instance_losses(test_dir, out / folder / "predictions.jsonl", args.object, mesh, min_score)
        breakdowns[folder] = {"lost": loss_counts(losses), "lost_bop_targets": loss_counts(bop_targets(losses)),
                              "lost_by_visibility": losses_by_visibility(losses)}
        lost_text.append(f"{label}: " + breakdown_text(breakdowns[folder]["lost"], min_score)
                         + f"\n  of BOP19's targets (visible >= {BOP_VISIBLE_FLOOR:g}): "
                         + breakdown_text(breakdowns[folder]["lost_bop_targets"], min_score)
                         + "\n  by visible fraction:\n" + visibility_text(breakdowns[folder]["lost_by_visibility"]))
    lost_text = "\n".join(lost_text)
    times = ", ".join(f"{k} {v:.0f} s" for k, v in pipe.timings.items())
    text = (f"# e2e accuracy: {args.object}, {args.config}, {args.train_minutes:g} min training\n\n"
            f"Held-out synthetic test set: {args.test_count} frames at {args.size} (seed {TEST_SEED}, photo "
            f"backgrounds, RealSense-like depth noise); {args.train_count} training frames at "
            f"{args.train_size} (seed {TRAIN_SEED}, {args.recipe} recipe: {' '.join(RECIPES[args.recipe])}); "
            f"test scenes {' '.join(SCENE)}; checkpoint {ckpt.name}; {cpu_line()}; {trained_text}. Recall = true positives / GT instances "
            f"(matching per image, greedy by score, error < threshold); median = median error of the "
            f"true positives at 10 cm; AR = BOP19 average recall.\n\n{table}\n\n{lost_text}\n\n"
            f"Stage times: {times}\n")
    (out / "results.md").write_text(text)
    (out / "results.json").write_text(json.dumps({"settings": settings, "checkpoint": str(ckpt),
                                                  "cpu": cpu_description(), "steps": trained["step"],
                                                  "budget_share": share, "losses": breakdowns, "results": data,
                                                  "stage_seconds": pipe.timings},
                                                 indent=1, default=float) + "\n")
    print("\n" + table + f"\n\n{trained_text}\n{lost_text}\nstage times: {times}\nwritten: {out / 'results.md'}, {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
