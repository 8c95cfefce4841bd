"""How accuracy grows with training time: the Ketchup recipe of ``bench/e2e_accuracy.py`` trained
for 30, then 60, then 120 CPU-minutes (``--minutes``), one run continued with `dope-hope train
--resume --time-budget MIN` (the same frames, the same seed: what a user does who trains on
after looking at the first result), evaluated on the same held-out frames at each point.

Stages (each a `dope-hope` command, as in ``bench/e2e_accuracy.py``, resumable at stage
granularity: rerun the same command to continue where a session stopped):

1. ``synth-train`` / ``synth-test``: the e2e bench's training set (seed 1, ``--recipe``) and
   held-out set (seed 1001, photo backgrounds, RealSense-like depth noise).
2. per budget B of ``--minutes``: ``train-B`` (`train --resume --time-budget B` on OUT/run:
   the first one starts the run from ``--init``, each later one continues it and plans the
   steps left again: the cosine starts again from its top, ``train.cosine_replan: restart``),
   the run's ``best.pt`` and ``summary.json`` copied to OUT/at_B/; ``infer-ls-B`` / ``infer-icp-B``
   (`infer --fast --depth auto`, the same with ``--icp``) and ``eval-B`` (`evaluate`, MeanSSD
   over every instance and over BOP19's targets).

``--from-e2e DIR`` starts from a finished ``bench/e2e_accuracy.py`` folder whose budget is the
first of ``--minutes`` and whose settings are this run's: its frames are linked and its run
copied (the first point is that run's model).

Prints and writes (OUT/results.md, OUT/results.json, OUT/curve.png) per budget: steps trained,
recall at 2 cm MeanSSD with -LS and with -LS + ICP, at 10 cm with -LS, the BOP19 targets with no
detection at the model's own threshold (-LS), and the gain of each doubling.

    python bench/training_curve.py --out runs/curve                    # 2 CPU cores: ~4 h in all
    python bench/training_curve.py --from-e2e runs/e2e_pre --out runs/curve   # reuse a 30-min e2e run
    python bench/training_curve.py --quick --out /tmp/curve_quick       # tiny: checks the plumbing
    python bench/training_curve.py --init none --out runs/curve_wide --train-set targets.symmetry=auto \
        model.lite.width=32 model.lite.feature_channels=128 model.lite.stage_channels=96   # a wider network
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from e2e_accuracy import (  # noqa: E402
    RECIPES,
    SCENE,
    TEST_SEED,
    TRAIN_SEED,
    TRAIN_SET,
    bop_targets,
    check_settings,
    instance_losses,
    loss_counts,
    losses_by_visibility,
    recorded_threshold,
    shared_defaults,
)

from dope_hope.devices import cpu_description, cpu_line  # noqa: E402
from dope_hope.io.atomic import atomic_write_text  # noqa: E402
from dope_hope.staged_run import CommandStages  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="work folder (default bench/out/curve, --quick: bench/out/curve_quick)")
    p.add_argument("--minutes", type=float, nargs="+", help="the budgets, increasing (default 30 60 120; "
                                                             "--quick 0.1 0.2)")
    p.add_argument("--mesh", type=Path, help="object mesh (default: the shared HOPE Ketchup textured.obj)")
    p.add_argument("--object", default="Ketchup", help="class name (default Ketchup)")
    p.add_argument("--backgrounds", type=Path, help="background photos of the test set (default: the shared "
                                                    "data's backgrounds/)")
    p.add_argument("--config", default="lite", help="training config (default lite)")
    p.add_argument("--init", default="pretrained", help="the weights the run starts from (`train --init`; "
                                                         "default pretrained)")
    p.add_argument("--recipe", choices=sorted(RECIPES), default="defaults", help="training frames (as e2e_accuracy)")
    p.add_argument("--train-set", nargs="+", default=list(TRAIN_SET), metavar="KEY=VALUE",
                   help=f"training config overrides (default {' '.join(TRAIN_SET)}); e.g. a wider lite network: "
                        "targets.symmetry=auto model.lite.width=32 model.lite.feature_channels=128 "
                        "model.lite.stage_channels=96 with --init none")
    p.add_argument("--train-count", type=int, help="training frames (default 12000; --quick 8)")
    p.add_argument("--test-count", type=int, help="held-out frames (default 200; --quick 3)")
    p.add_argument("--workers", type=int, default=2, help="synth render processes (default 2)")
    p.add_argument("--from-e2e", type=Path, metavar="DIR", help="a finished bench/e2e_accuracy.py folder "
                                                                 "trained for the first budget")
    p.add_argument("--quick", action="store_true", help="tiny sizes and budgets (numbers meaningless)")
    args = p.parse_args(argv)
    q = args.quick
    args.minutes = args.minutes or ([0.1, 0.2] if q else [30.0, 60.0, 120.0])
    if any(b <= a for a, b in zip(args.minutes, args.minutes[1:])) or args.minutes[0] <= 0:
        p.error(f"--minutes {' '.join(map(str, args.minutes))}: budgets must be positive and increasing")
    args.train_count = args.train_count or (8 if q else 12000)
    args.test_count = args.test_count or (3 if q else 200)
    args.train_size, args.size = ("64x64", "160x120") if q else ("256x192", "640x480")
    args.out = args.out or REPO / "bench" / "out" / ("curve_quick" if q else "curve")
    shared_defaults(p, args)
    return args


def e2e_settings(args: argparse.Namespace) -> dict:
    """The settings ``bench/e2e_accuracy.py`` records for the same frames and first budget."""
    settings = {"mesh": str(args.mesh.resolve()), "object": args.object, "config": args.config,
                "train_minutes": args.minutes[0], "train_count": args.train_count,
                "train_size": args.train_size, "train_set": list(args.train_set), "scene": SCENE,
                "test_count": args.test_count, "size": args.size, "device": None,
                "backgrounds": None if args.backgrounds is None else str(args.backgrounds.resolve()),
                "quick": args.quick, "train_seed": TRAIN_SEED, "test_seed": TEST_SEED}
    if args.recipe != "plain":
        settings["recipe"] = args.recipe
    if args.init != "none":
        settings["init"] = args.init if args.init in ("pretrained", "demo") else str(Path(args.init).resolve())
    return settings


def adopt_e2e_run(source: Path, out: Path, settings: dict, first: float) -> None:
    """Start ``out`` from a finished e2e folder: its frames linked, its run copied, the stages
    it did marked done (once; a folder already started is left as it is)."""
    if (out / "run").exists():
        return
    recorded = json.loads((source / "e2e_settings.json").read_text()) if (source / "e2e_settings.json").is_file() else None
    if recorded != settings:
        raise SystemExit(f"--from-e2e {source}: not an e2e_accuracy.py run with these settings "
                         f"(its e2e_settings.json must equal {json.dumps(settings)})")
    for stage in ("synth-train", "synth-test", "train"):
        if not (source / "stages" / f"{stage}.json").is_file():
            raise SystemExit(f"--from-e2e {source}: its stage {stage} is not done")
    out.mkdir(parents=True, exist_ok=True)
    (out / "stages").mkdir(exist_ok=True)
    for name in ("train", "test"):
        (out / name).symlink_to((source / name).resolve())
    shutil.copytree(source / "run", out / "run.partial")
    os.replace(out / "run.partial", out / "run")
    for stage, copy in (("synth-train", "synth-train"), ("synth-test", "synth-test"), ("train", f"train-{first:g}")):
        shutil.copyfile(source / "stages" / f"{stage}.json", out / "stages" / f"{copy}.json")


def keep_point(run_dir: Path, point_dir: Path) -> Path:
    """Copy the run's best.pt (else last.pt) and summary.json to ``point_dir`` (once; atomic)."""
    ckpt = point_dir / "best.pt"
    if ckpt.is_file():
        return ckpt
    point_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run_dir / "summary.json", point_dir / "summary.json")
    source = run_dir / "best.pt" if (run_dir / "best.pt").is_file() else run_dir / "last.pt"
    shutil.copyfile(source, point_dir / "best.pt.partial")
    os.replace(point_dir / "best.pt.partial", ckpt)
    return ckpt


def measure_point(pipe: CommandStages, args: argparse.Namespace, out: Path, minutes: float) -> dict:
    """Train to ``minutes``, keep the model, run and evaluate it; the point's figures."""
    mesh, test_dir, run_dir = args.mesh.resolve(), out / "test", out / "run"
    tag = f"{minutes:g}"
    train = ["train", "--config", args.config, "--data", out / "train", "--object", args.object, "--mesh", mesh,
             "--out", run_dir, "--time-budget", minutes, "--resume", "--no-progress", "--init", args.init]
    sets = list(args.train_set)
    if args.quick:  # a tiny-input run for the small budget: checks the plumbing only
        train += ["--batch-size", "2", "--workers", "0"]
        sets += ["input.size=[64,64]", "train.threads=1"]
    train += ["--set", *sets]
    pipe.stage(f"train-{tag}", train)
    point = out / f"at_{tag}"
    ckpt = keep_point(run_dir, point)
    infer = ["infer", test_dir, "--weights", ckpt, "--mesh", mesh, "--no-overlay", "--no-progress",
             "--min-score", "0", "--fast", "--depth", "auto"]
    pipe.stage(f"infer-ls-{tag}", infer + ["--out", point / "infer_ls"])
    pipe.stage(f"infer-icp-{tag}", infer + ["--icp", "--out", point / "infer_icp"])
    evaluate = ["evaluate", "-p", point / "infer_ls" / "predictions.jsonl", point / "infer_icp" / "predictions.jsonl",
                "--method", "LS", "LS-ICP", "-d", test_dir, "--mesh", f"{args.object}={mesh}", "--no-progress",
                "--metric", "meanssd", "--no-bop-ar"]
    pipe.stage(f"eval-{tag}", evaluate + ["--out", point / "eval"])
    pipe.stage(f"eval-bop19-{tag}", evaluate + ["--min-visible", "bop19", "--out", point / "eval_bop19"])
    summary = json.loads((point / "summary.json").read_text())
    every = json.loads((point / "eval" / "summary.json").read_text())["methods"]
    bop = json.loads((point / "eval_bop19" / "summary.json").read_text())["methods"]
    min_score = recorded_threshold(ckpt, args.object)
    every_instance = instance_losses(test_dir, point / "infer_ls" / "predictions.jsonl", args.object, mesh, min_score)
    losses = bop_targets(every_instance)
    counts = loss_counts(losses)
    return {"minutes": minutes, "steps": summary["step"], "budget_used_s": summary["budget_used_s"],
            "status": summary["status"], "best_val_kp_acc": summary.get("best_val_kp_acc"),
            "recall_2cm_ls": every["LS"]["overall"]["recall_2cm"],
            "recall_2cm_ls_icp": every["LS-ICP"]["overall"]["recall_2cm"],
            "recall_10cm_ls": every["LS"]["overall"]["recall_10cm"],
            "bop_recall_2cm_ls": bop["LS"]["overall"]["recall_2cm"],
            "bop_recall_2cm_ls_icp": bop["LS-ICP"]["overall"]["recall_2cm"],
            "bop_recall_10cm_ls": bop["LS"]["overall"]["recall_10cm"],
            "min_score": min_score, "bop_targets": len(losses), "bop_no_detection": counts["no detection"],
            "lost_by_visibility": losses_by_visibility(every_instance)}


def curve_table(points: list[dict]) -> str:
    """Markdown table of the points, each with its gain over the one before."""
    rows = ["| budget (min) | steps | 2 cm -LS | 2 cm -LS+ICP | 10 cm -LS | BOP targets: 2 cm -LS | "
            "BOP targets: 2 cm -LS+ICP | BOP targets: no detection (-LS) |", "|" + "---|" * 8]
    for p in points:
        rows.append(f"| {p['minutes']:g} | {p['steps']} | {100 * p['recall_2cm_ls']:.1f} % | "
                    f"{100 * p['recall_2cm_ls_icp']:.1f} % | {100 * p['recall_10cm_ls']:.1f} % | "
                    f"{100 * p['bop_recall_2cm_ls']:.1f} % | {100 * p['bop_recall_2cm_ls_icp']:.1f} % | "
                    f"{p['bop_no_detection']} of {p['bop_targets']} "
                    f"({100 * p['bop_no_detection'] / max(1, p['bop_targets']):.1f} %) |")
    return "\n".join(rows)


def visibility_table(points: list[dict]) -> str:
    """Markdown table: per visible-fraction band, the instances with no detection (-LS, the
    model's own threshold) and those within 2 cm, at each budget."""
    bands = list(points[0]["lost_by_visibility"])
    rows = ["| visible | instances | " + " | ".join(f"{p['minutes']:g} min: no detection / within 2 cm" for p in points)
            + " |", "|" + "---|" * (2 + len(points))]
    for band in bands:
        counts = [p["lost_by_visibility"][band] for p in points]
        rows.append(f"| {band} | {sum(counts[0].values())} | " + " | ".join(
            f"{c['no detection']} / {c['within 2 cm']}" for c in counts) + " |")
    return "\n".join(rows)


def plot_curve(points: list[dict], path: Path, title: str) -> None:
    """Recall against training minutes (log2 axis), one line per measure."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    minutes = [p["minutes"] for p in points]
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for key, label in (("recall_2cm_ls", "2 cm, -LS"), ("recall_2cm_ls_icp", "2 cm, -LS + ICP"),
                       ("recall_10cm_ls", "10 cm, -LS")):
        ax.plot(minutes, [100 * p[key] for p in points], marker="o", label=label)
    ax.plot(minutes, [100 * p["bop_no_detection"] / max(1, p["bop_targets"]) for p in points], marker="x",
            linestyle="--", color="grey", label="no detection (BOP targets)")
    ax.set_xscale("log", base=2)
    ax.set_xticks(minutes, [f"{m:g}\n({p['steps']} steps)" for m, p in zip(minutes, points)])
    ax.set_xlabel("training minutes (2 CPU cores)")
    ax.set_ylabel("% of held-out instances (MeanSSD)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".partial.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out: Path = args.out.resolve()
    settings = e2e_settings(args)
    if args.from_e2e is not None:
        adopt_e2e_run(args.from_e2e.resolve(), out, settings, args.minutes[0])
    check_settings(out, settings)  # the budgets are not recorded: a folder's curve may grow
    print(cpu_line(), flush=True)
    print(f"training curve: {args.object}, {args.config} from {args.init}, budgets {args.minutes} min, "
          f"{os.cpu_count()} CPU core(s); work folder {out}", flush=True)
    pipe = CommandStages(out, cwd=REPO)
    common = ["--mesh", args.mesh.resolve(), "--class-name", args.object, "--no-progress", "--workers", args.workers]
    pipe.stage("synth-train", ["synth", *common, "--set", *RECIPES[args.recipe], "--size", args.train_size,
                               "--out", out / "train", "--count", args.train_count, "--seed", TRAIN_SEED])
    test = ["synth", *common, "--set", *SCENE, "--size", args.size, "--out", out / "test", "--count",
            args.test_count, "--seed", TEST_SEED, "--depth-noise"]
    if args.backgrounds is not None:
        test += ["--backgrounds", args.backgrounds.resolve()]
    pipe.stage("synth-test", test)
    points = []
    for minutes in args.minutes:
        points.append(measure_point(pipe, args, out, minutes))
        print(curve_table(points), flush=True)
    table = curve_table(points) + "\n\nBy visible fraction (every instance; -LS at the model's own threshold):\n\n" \
        + visibility_table(points)
    cpu = cpu_description()
    flags = ", ".join(k for k, v in cpu["flags"].items() if v) or "no vector flags"
    title = f"{args.object}, {args.config} from {args.init}; {cpu['model']} ({flags}), {os.cpu_count()} cores"
    plot_curve(points, out / "curve.png", title)
    text = (f"# Training curve: {args.object}, {args.config}, budgets {args.minutes} min\n\n"
            f"{cpu_line()}; one run continued with `train --resume --time-budget`; {args.test_count} held-out "
            f"frames at {args.size} (seed {TEST_SEED}); recall at 2 / 10 cm MeanSSD over every instance "
            f"(HOPE's convention) and over BOP19's targets; no detection at the model's own threshold; the breakdown "
            f"by visible fraction below 0.1 counts no BOP19 target.\n\n"
            f"{table}\n")
    atomic_write_text(out / "results.md", text)
    atomic_write_text(out / "results.json", json.dumps({"settings": settings, "cpu": cpu_description(),
                                                        "points": points, "stage_seconds": pipe.timings},
                                                       indent=1, default=float) + "\n")
    print(f"\n{table}\nwritten: {out / 'results.md'}, {out / 'results.json'}, {out / 'curve.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
