"""Make the pretrained lite start (dope_hope/assets/pretrained_lite.pt) with one command.

Stages (each a `dope-hope` command run as a subprocess by
:class:`dope_hope.staged_run.CommandStages`, logged to OUT/logs/; a stage whose marker
OUT/stages/<stage>.json exists is skipped, an interrupted synth resumes frame by frame and an
interrupted training with --resume, so rerunning the same command continues the run and ends
with the same weights):

1. ``synth-train`` / ``synth-val``: `dope-hope synth --procedural --config pretrain` (seeds 21
   and 22): a new object in every 256x192 frame, of eight shapes (boxes, cans, squeeze
   bottles, jars, tubes, pouches, rounded boxes, irregular bodies), scaled 0.5-2.2x, at
   0.18-1.4 m, a quarter of the frames empty, over the photographs of ``--photos`` (the 47 of
   `python bench/training_photos.py --out photos`), table-top clutter and sensor artefacts.
2. ``train``: `dope-hope train --config lite` for ``--steps`` optimizer steps (not a time
   budget: the same steps on any machine), from ``--init`` (the recipe's: the start shipped
   before it, ``git show c9a779e:dope_hope/assets/pretrained_lite.pt``), with wider crop
   scales and offsets than the one-object recipe (objects from ~15 px to filling the frame).
3. ``export``: OUT/pretrained_lite.pt, the run's last weights without training state, marked
   as a pretrained start (`infer` takes it only as the zero-training detector of a mesh).

    python bench/training_photos.py --out photos
    git show c9a779e:dope_hope/assets/pretrained_lite.pt > start_v1.pt
    python tools/pretrain_start.py --out pre --photos photos --init start_v1.pt   # 2 CPU cores (AMX): ~1.5 h
    cp pre/pretrained_lite.pt dope_hope/assets/pretrained_lite.pt

Never pretrain on a benchmark's objects or textures (the HOPE Ketchup, the grocery meshes of
bench/multi_object.py): the procedural objects are made from code, the photographs are
background scenes.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dope_hope.model.checkpoint import PRETRAINED_START_SOURCE, save_inference_checkpoint
from dope_hope.staged_run import CommandStages

REPO = Path(__file__).resolve().parent.parent
#: Synth seeds of the training and validation frames.
TRAIN_SEED, VAL_SEED = 21, 22
#: Training overrides of the recipe: a fixed step count, wider crop zoom and offsets.
TRAIN_SET = ("train.time_limit_min=null", "augment.scale=[0.6,1.6]", "augment.crop_jitter=0.5")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="work folder (frames, run, logs, the start)")
    p.add_argument("--photos", type=Path, required=True, help="background photographs "
                                                              "(python bench/training_photos.py --out DIR)")
    p.add_argument("--init", required=True, help="weights the run starts from: a dope-hope checkpoint (the "
                                                 "recipe's: the start of commit c9a779e), demo or none")
    p.add_argument("--count", type=int, default=16000, help="training frames (default 16000)")
    p.add_argument("--val-count", type=int, default=300, help="validation frames (default 300)")
    p.add_argument("--steps", type=int, default=16000, help="optimizer steps of 16 crops (default 16000)")
    p.add_argument("--workers", type=int, default=1, help="synth render processes (default 1: one "
                                                          "already fills 2 cores)")
    args = p.parse_args(argv)
    if not args.photos.is_dir() or not any(args.photos.iterdir()):
        p.error(f"--photos {args.photos}: not a folder of photographs")
    out = args.out.resolve()
    stages = CommandStages(out, cwd=REPO)
    synth = ["synth", "--procedural", "--config", "pretrain", "--size", "256x192", "--workers", args.workers,
             "--backgrounds", args.photos.resolve(), "--no-progress"]
    stages.stage("synth-train", [*synth, "--out", out / "train", "--count", args.count, "--seed", TRAIN_SEED])
    stages.stage("synth-val", [*synth, "--out", out / "val", "--count", args.val_count, "--seed", VAL_SEED])
    train = ["train", "--out", out / "run", "--no-progress"]
    if (out / "run" / "last.pt").is_file():
        train += ["--resume"]
    else:
        train += ["--config", "lite", "--init", args.init, "--data", out / "train", "--val", out / "val",
                  "--object", "Object", "--steps", args.steps, "--set", *TRAIN_SET]
    stages.stage("train", train)
    start = save_inference_checkpoint(out / "run" / "last.pt", out / "pretrained_lite.pt",
                                      source=PRETRAINED_START_SOURCE)
    print(f"the start: {start}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
