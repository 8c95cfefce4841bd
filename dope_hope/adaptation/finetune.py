"""One round's fine-tuning: the labelled frames mixed with synthetic frames the model was
trained on, trained from the round's starting weights by `dope-hope train`'s entry point
(:func:`dope_hope.training.trainer.train`), resumable, and the adapted model's record.

**The mix** (:func:`synthetic_mix`): ``synthetic_ratio`` synthetic frames per labelled frame
(at most ``max_synthetic``), drawn without replacement by a seeded generator of
(``finetune.seed``, round) from the synthetic folders, linked (symbolic links, no copies)
into the round's ``mix/`` folder, which the trainer reads beside ``labels/`` as a second
``--data`` folder. The ratio lives here, not in the trainer: a folder of links is how any
`dope-hope train` run is given a subset of a dataset.

**Training** (:func:`finetune_round`): a new run from the round's starting weights (``--init``;
its recipe the checkpoint's own, with ``finetune.lr`` and the round's share of the time budget
or ``finetune.steps``), or, when the round's run was interrupted, its ``last.pt`` resumed
(``--resume``): the same result as an uninterrupted run, as the trainer resumes.

**The round's model** (``model.pt`` beside the run): the run's final weights (its ``last.pt``,
the end of its schedule; not its ``best.pt``, which the trainer chooses on the validation
share of the round's frames: 3 frames of a round of 100, chance) with the score thresholds of
the model the round started from (an ``--init`` run starts without them, and its few
validation frames cannot choose new ones; `dope-hope calibrate` on held-out frames can).
"""
from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dope_hope.adaptation.settings import FineTuneSettings
from dope_hope.errors import ConfigError
from dope_hope.io.atomic import atomic_write_stream, atomic_write_text
from dope_hope.io.dope_json import list_dope_frames
from dope_hope.model.checkpoint import load_checkpoint, with_min_scores
from dope_hope.model.info import ModelInfo
from dope_hope.training.settings import TrainJob
from dope_hope.training.trainer import train

#: The marker of a round whose training ended (its summary), beside ``train/``.
TRAINED_MARKER = "trained.json"
#: The round's model (module docstring), beside ``train/``.
ROUND_MODEL = "model.pt"
#: The trainer's statuses of a run that ended by itself (not interrupted).
FINISHED = ("completed", "time_limit")


def synthetic_mix(folder: Path, synthetic: Sequence[Path], labels: int, settings: FineTuneSettings,
                  round_index: int) -> int:
    """Link the round's synthetic frames into ``folder`` (module docstring; made whole or not
    at all, the same frames for the same seed and round); returns their number (0: no folder)."""
    want = int(round(settings.synthetic_ratio * labels))
    if settings.max_synthetic is not None:
        want = min(want, settings.max_synthetic)
    frames = [p for d in synthetic for p in list_dope_frames(d)]
    want = min(want, len(frames))
    if want <= 0:
        return 0
    if folder.is_dir() and len(list(folder.glob("*.json"))) == want:
        return want
    rng = np.random.default_rng([int(settings.seed), int(round_index)])
    chosen = sorted(rng.choice(len(frames), size=want, replace=False).tolist())
    staging = folder.with_name(folder.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    siblings: dict[Path, dict[str, list[Path]]] = {}
    for k, i in enumerate(chosen):
        json_path = frames[i]
        by_stem = siblings.get(json_path.parent)
        if by_stem is None:  # one listing per folder, not one glob per frame
            by_stem = siblings[json_path.parent] = {}
            for p in json_path.parent.iterdir():
                by_stem.setdefault(p.name.split(".", 1)[0], []).append(p)
        stem = json_path.name.split(".", 1)[0]
        for p in by_stem.get(stem, []):
            os.symlink(p.resolve(), staging / f"{k:06d}{p.name[len(stem):]}")
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(staging, folder)
    return want


def finetune_round(start: Path, data: Sequence[Path], frames: int, out: Path, mesh: Path, mesh_units: str | None,
                   settings: FineTuneSettings, minutes: float, progress: bool = True) -> dict[str, Any]:
    """Train the round (module docstring) into ``out`` from the weights ``start`` on the
    ``data`` folders (``frames`` frames in all); the object's ``mesh`` (its box and
    symmetries, as `train --mesh`).
    Returns the round's record: ``status`` (the trainer's), ``best`` (the round's model, when
    it finished: a status of :data:`FINISHED`); a finished round is not run again (its marker
    :data:`TRAINED_MARKER` beside ``out``)."""
    marker = out.parent / TRAINED_MARKER
    if marker.is_file():
        return json.loads(marker.read_text())
    ckpt = load_checkpoint(start)
    entries = ckpt.get("objects") or [ckpt["object"]]
    if len(entries) != 1:
        raise ConfigError(f"{start}: a model of {len(entries)} objects; adapt fine-tunes one-object models")
    overrides: dict[str, Any] = {"train": {"seed": int(settings.seed)}}
    if settings.steps is not None:
        overrides["train"]["steps"] = int(settings.steps)
    else:
        overrides["train"]["time_limit_min"] = float(minutes)
    recipe_batch = int((ckpt["config"].get("train") or {}).get("batch_size") or 16)
    overrides["train"]["batch_size"] = int(settings.batch_size or min(recipe_batch, max(1, int(0.8 * frames))))
    if settings.lr is not None:
        overrides["train"]["lr"] = float(settings.lr)
    last = out / "last.pt"
    resume = last if last.is_file() else None
    job = TrainJob(data=list(data), object_name=str(entries[0]["class_name"]), out=out, resume=resume,
                   mesh=mesh, init_weights=None if resume else start,
                   init_reason="" if resume else f"the weights of {start} (adapt)", device="cpu",
                   progress=progress, overrides=overrides, units={"": mesh_units} if mesh_units else {})
    summary = train(job, {} if resume else dict(ckpt["config"]))
    if summary.get("status") not in FINISHED:
        return {"status": summary.get("status")}  # interrupted: the same command resumes it
    model = round_model(last, start, out.parent / ROUND_MODEL)
    record = {"status": summary.get("status"), "step": summary.get("step"), "weights": str(model),
              "val_kp_acc": summary.get("val_kp_acc")}
    atomic_write_text(marker, json.dumps(record, indent=1, default=str) + "\n")
    return record


def round_model(final: Path, start: Path, dst: Path) -> Path:
    """Write the round's model (module docstring) to ``dst`` (atomically): the checkpoint
    ``final`` with the score thresholds of ``start`` (the model's own and each object's, where
    ``start`` records them)."""
    info = ModelInfo.from_checkpoint(load_checkpoint(start), start)
    ckpt = with_min_scores(load_checkpoint(final), final, info.min_score,
                           {o.class_name: o.min_score for o in info.objects if o.min_score is not None})
    atomic_write_stream(dst, lambda f: torch.save(ckpt, f))
    return dst


def record_adaptation(src: Path, dst: Path, adapted: dict[str, Any]) -> Path:
    """Copy the checkpoint ``src`` to ``dst`` (atomically) with ``adapted``, what the model was
    adapted on (plain data: the starting model, the frames, each round's label counts, the
    synthetic share, the settings), under the checkpoint's key ``adapted``."""
    ckpt = load_checkpoint(src)
    ckpt["adapted"] = json.loads(json.dumps(adapted, default=str))
    atomic_write_stream(dst, lambda f: torch.save(ckpt, f))
    return dst
