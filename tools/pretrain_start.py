"""Make the pretrained lite start (dope_hope/assets/pretrained_lite.pt) with one command.

Stages (each a `dope-hope` command run as a subprocess by
:class:`dope_hope.staged_run.CommandStages`, logged to OUT/logs/; a stage whose marker
OUT/stages/<stage>.json exists is skipped, an interrupted synth resumes frame by frame and an
interrupted training with --resume, so rerunning the same command continues the run and ends
with the same weights; a folder holding a run of other settings is refused, exit status 2):

1. ``synth-train`` / ``synth-val``: `dope-hope synth --procedural` at 256x192 over the
   photographs of ``--photos`` (the 47 of `python bench/training_photos.py --out photos`), with
   the recipe's synth config and seeds (:data:`RECIPES`):

   - ``categories`` (the shipped start's): `--config procedural`, a new box, can or squeeze
     bottle of HOPE size with a packaging-like texture in every frame, one to three instances
     at table-top distances (seeds 31 and 32);
   - ``categories-again``: the same on 16,000 new frames (seeds 33 and 34), run from the
     ``categories`` start (``git show 058b72b:dope_hope/assets/pretrained_lite.pt``): 32,000
     steps over photographs in all;
   - ``wide``: `--config pretrain`, a new object of eight shapes (boxes, cans, squeeze bottles,
     jars, tubes, pouches, rounded boxes, irregular bodies), scaled 0.5-2.2x, at 0.18-1.4 m, a
     quarter of the frames empty, table-top clutter and sensor artefacts (seeds 21 and 22);
     with wider crop scales and offsets in training. It did not beat ``categories``.
2. ``train``: `dope-hope train --config lite` for the recipe's step count (16,000; not a time budget:
   the same steps on any machine), from ``--init`` (the start shipped before the recipe:
   ``git show c9a779e:dope_hope/assets/pretrained_lite.pt`` for ``categories`` and ``wide``,
   ``git show 058b72b:dope_hope/assets/pretrained_lite.pt`` for ``categories-again``).
3. ``export``: OUT/pretrained_lite.pt, the run's last weights without training state, marked
   as a pretrained start (`infer` takes it only as the zero-training detector of a mesh).

    python bench/training_photos.py --out photos
    git show c9a779e:dope_hope/assets/pretrained_lite.pt > start_v1.pt
    python tools/pretrain_start.py --out pre --photos photos --init start_v1.pt   # 2 CPU cores (AMX): ~50 min
    cp pre/pretrained_lite.pt dope_hope/assets/pretrained_lite.pt

Never pretrain on a benchmark's objects or textures (the HOPE Ketchup, the grocery meshes of
bench/multi_object.py): the procedural objects are made from code, the photographs are
background scenes.
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path

from dope_hope.model.checkpoint import PRETRAINED_START_SOURCE, save_inference_checkpoint
from dope_hope.staged_run import CommandStages, settings_changed

REPO = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Recipe:
    """A pretraining recipe: the synth config of its frames and their seeds (training,
    validation), its optimizer steps of 16 crops, and its training overrides."""

    synth_config: str
    train_seed: int
    val_seed: int
    steps: int
    train_set: tuple[str, ...]


#: The recipes; the first is the shipped start's.
RECIPES = {
    "categories": Recipe("procedural", 31, 32, 16000, ("train.time_limit_min=null",)),
    "categories-again": Recipe("procedural", 33, 34, 16000, ("train.time_limit_min=null",)),
    "wide": Recipe("pretrain", 21, 22, 16000,
                   ("train.time_limit_min=null", "augment.scale=[0.6,1.6]", "augment.crop_jitter=0.5")),
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="work folder (frames, run, logs, the start)")
    p.add_argument("--photos", type=Path, required=True, help="background photographs "
                                                              "(python bench/training_photos.py --out DIR)")
    p.add_argument("--init", required=True, help="weights the run starts from: a dope-hope checkpoint (the "
                                                 "recipe's: the start shipped before it), demo or none")
    p.add_argument("--recipe", choices=sorted(RECIPES), default=next(iter(RECIPES)),
                   help="frames and training (default: categories, the shipped start's)")
    p.add_argument("--count", type=int, default=16000, help="training frames (default 16000)")
    p.add_argument("--val-count", type=int, default=300, help="validation frames (default 300)")
    p.add_argument("--steps", type=int, help="optimizer steps of 16 crops (default: the recipe's, 16000)")
    p.add_argument("--workers", type=int, default=1, help="synth render processes (default 1: one "
                                                          "already fills 2 cores)")
    args = p.parse_args(argv)
    if not args.photos.is_dir() or not any(args.photos.iterdir()):
        p.error(f"--photos {args.photos}: not a folder of photographs")
    recipe = RECIPES[args.recipe]
    out = args.out.resolve()
    steps = recipe.steps if args.steps is None else args.steps
    for flag, value in (("--steps", steps), ("--count", args.count), ("--val-count", args.val_count)):
        if value < 1:
            p.error(f"{flag} {value}: must be at least 1")
    chosen = {"recipe": args.recipe, **asdict(recipe), "train_set": list(recipe.train_set), "count": args.count,
              "val_count": args.val_count, "steps": steps, "init": str(args.init)}
    changed = settings_changed(out / "pretrain_settings.json", chosen)
    if changed:
        p.error(f"--out {out}: holds a run with other settings ({', '.join(changed)}); use another folder or delete it")
    stages = CommandStages(out, cwd=REPO)
    synth = ["synth", "--procedural", "--config", recipe.synth_config, "--size", "256x192", "--workers",
             args.workers, "--backgrounds", args.photos.resolve(), "--no-progress"]
    stages.stage("synth-train", [*synth, "--out", out / "train", "--count", args.count, "--seed", recipe.train_seed])
    stages.stage("synth-val", [*synth, "--out", out / "val", "--count", args.val_count, "--seed", recipe.val_seed])
    train = ["train", "--out", out / "run", "--no-progress"]
    if (out / "run" / "last.pt").is_file():
        train += ["--resume"]
    else:
        # a start has no threshold of its own (the zero-training detector drops it): no choice at the end
        train += ["--config", "lite", "--init", args.init, "--data", out / "train", "--val", out / "val",
                  "--object", "Object", "--steps", steps, "--set", *recipe.train_set,
                  "train.calibrate_thresholds=false"]
    stages.stage("train", train)
    start = save_inference_checkpoint(out / "run" / "last.pt", out / "pretrained_lite.pt",
                                      source=PRETRAINED_START_SOURCE)
    print(f"the start: {start}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
