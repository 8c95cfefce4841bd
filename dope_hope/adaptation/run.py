"""`dope-hope adapt` as a library: :func:`adapt` teaches a model the lab's own domain from its
unlabelled RGB-D frames, with the depth as the teacher.

The loop, in ``out/`` (each step resumes where it stopped; the same command continues):

1. ``frames/``: the unlabelled frames, read once from the recording / video / folder
   (:mod:`dope_hope.adaptation.frames`; at most ``max_frames``).
2. For each round r (``finetune.rounds``): ``round_r/labels/`` (the model of the round before,
   round 1 the given weights, labels the frames: :mod:`dope_hope.adaptation.labelling`, its
   first pass logged frame by frame in ``round_r/detected.jsonl``, the sequences where it
   confirmed nothing labelled again at ``carry.seed_scales`` in ``round_r/seeded.jsonl``, written by
   :mod:`dope_hope.adaptation.label_set`; ``preview_round_r.png`` with ``preview``), ``round_r/mix/``
   (synthetic frames, :func:`dope_hope.adaptation.finetune.synthetic_mix`), ``round_r/train/`` (the
   fine-tuning, :func:`dope_hope.adaptation.finetune.finetune_round`, the time budget shared by the
   rounds).
3. ``adapted.pt``: the last round's model, recording what it adapted on (``adapted``).

``job.json`` records the job (weights, mesh, inputs, settings); a folder of another job is
refused, so a resumed run is the same job.
"""
from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from dope_hope.adaptation.finetune import FINISHED, finetune_round, record_adaptation, synthetic_mix
from dope_hope.adaptation.frames import open_unlabelled
from dope_hope.adaptation.label_set import FrameStore, LabelCounts, write_label_set
from dope_hope.adaptation.labelling import DepthLabeller, LabelledFrame, unseeded
from dope_hope.adaptation.settings import AdaptConfig
from dope_hope.errors import ConfigError, DopeHopeError, InputFileError
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.camera import ImageCamera
from dope_hope.io.dope_json import list_dope_frames
from dope_hope.io.paths import output_dir, require_file
from dope_hope.model.checkpoint import load_checkpoint
from dope_hope.staged_run import settings_changed

#: The adapted model's file in ``out``.
ADAPTED_NAME = "adapted.pt"


@dataclass
class AdaptResult:
    """status: "completed", or the trainer's when a round's training was interrupted.
    weights: the adapted model (None until the last round finished). rounds: each round's
    label counts and training record."""

    status: str
    weights: Path | None
    rounds: list[dict[str, Any]] = field(default_factory=list)


def recorded_synthetic(weights: Path) -> list[Path]:
    """The training folders a checkpoint records (its run's ``--data``) that exist here."""
    job = ((load_checkpoint(weights).get("extra") or {}).get("job") or {})
    return [Path(p) for p in job.get("data") or [] if Path(p).is_dir()]


def _check_synthetic(folders: Sequence[Path]) -> list[Path]:
    for d in folders:
        if not d.is_dir():
            raise InputFileError(d, "--synthetic: folder not found")
        if not list_dope_frames(d):
            raise InputFileError(d, "--synthetic: no DOPE frames (NNNNNN.json beside an image) in this folder")
    return list(folders)


def _read_frames(source, store: FrameStore, max_frames: int | None, progress: bool) -> None:
    """Fill the store from the source (at most ``max_frames``) and mark it complete."""
    store.folder.mkdir(parents=True, exist_ok=True)
    try:
        bar = tqdm(total=max_frames or source.length, desc="frames", unit="frame", disable=not progress)
        for g in source.grab():
            if max_frames is not None and len(store) >= max_frames:
                break
            store.add(g.load())
            bar.update(1)
        bar.close()
    finally:
        source.close()
    if not len(store):
        raise InputFileError(source.name, "no frame could be read")
    store.finish(source.name)


def _detected_labels(store: FrameStore, labeller: DepthLabeller, log: Path, progress: bool,
                     indices: Sequence[int] | None = None) -> list[LabelledFrame]:
    """The first pass (detected labels) of the store's frames ``indices`` (default all),
    logged a line per frame to ``log``: an interrupted pass goes on after the frames it logged
    (a cut last line is done again), and the labels are always read back from the log, so a
    resumed round is the one that ran through."""
    indices = list(range(len(store))) if indices is None else list(indices)
    done: list[str] = []
    if log.is_file():
        for line in log.read_text().splitlines():
            try:
                if len(done) >= len(indices) or json.loads(line)["index"] != indices[len(done)]:
                    break
            except (ValueError, KeyError):
                break
            done.append(line)
        atomic_write_text(log, "".join(line + "\n" for line in done))
    with open(log, "a") as f:
        for i in tqdm(indices[len(done):], desc=f"{log.stem} {log.parent.name}", unit="frame",
                      initial=len(done), total=len(indices), disable=not progress):
            f.write(json.dumps(labeller.label_frame(store.frame(i)).to_record()) + "\n")
            f.flush()
    return [LabelledFrame.from_record(json.loads(line)) for line in log.read_text().splitlines()]


def _seed_predictor(model: Path, mesh: Path, mesh_units: str | None, cfg: AdaptConfig) -> DopePredictor:
    """The round's model at the working sizes ``carry.seed_scales`` (the labelling's other
    inference options as they are)."""
    seeding = replace(cfg.infer, multiscale=replace(cfg.infer.multiscale, scales=tuple(cfg.carry.seed_scales)))
    return DopePredictor(model, mesh=mesh, mesh_units=mesh_units, options=seeding.given())


def _label_round(store: FrameStore, predictor: DopePredictor, cfg: AdaptConfig, folder: Path,
                 preview: Path | None, extra: dict, progress: bool, seeder: Callable[[], DopePredictor]) -> LabelCounts:
    """One round's labels (module docstring, step 2): the first pass; the frames of the
    sequences where it confirmed nothing again with ``seeder()`` (``carry.seed_scales``; its
    result kept where it confirms a detection); the carrying; the label set written."""
    labeller = DepthLabeller(predictor, cfg)
    folder.parent.mkdir(parents=True, exist_ok=True)
    frames = _detected_labels(store, labeller, folder.parent / "detected.jsonl", progress)
    todo = unseeded(frames) if cfg.carry.enabled and cfg.carry.seed_scales else []
    if todo:
        again = _detected_labels(store, DepthLabeller(seeder(), cfg), folder.parent / "seeded.jsonl", progress, todo)
        for i, lf in zip(todo, again):
            if lf.detected:
                frames[i] = lf
    labeller.carry(frames, store.depth)
    cuboids = {o.class_name: (o.cuboid_size_m, o.cuboid_center_m) for o in predictor.objects}
    return write_label_set(store, folder, frames, cuboids, extra, preview)


def adapt(inputs: Sequence[str], weights: str | Path, mesh: str | Path, out: str | Path, *,
          mesh_units: str | None = None, synthetic: Sequence[str | Path] | None = None,
          settings: AdaptConfig | Mapping[str, Any] | None = None, camera: ImageCamera | None = None,
          depth: str | Path | None = None, depth_scale_mm: float | None = None, image_topic: str | None = None,
          depth_topic: str | None = None, camera_info_topic: str | None = None, max_frames: int | None = None,
          preview: bool = False, progress: bool = True,
          note: Callable[[str], None] = lambda message: None) -> AdaptResult:
    """Adapt the model ``weights`` (a one-object dope-hope checkpoint) to the domain of the
    unlabelled frames ``inputs`` (module docstring).

    Args:
        inputs: a recording (ROS 1 / 2 bag, MCAP), a video (with ``camera`` and a ``depth``
            folder), or image files / folders / globs with their depth.
        mesh: the object's mesh (``mesh_units``: its unit, default by suffix).
        out: the job's folder. synthetic: the synthetic training folders to mix in (default:
            those the checkpoint records, where they exist).
        settings: :class:`AdaptConfig` or a mapping of its sections over the defaults.
        max_frames: read at most this many frames. preview: write each round's contact sheet.
        note: told each step's outcome in one line.

    Raises DopeHopeError (one line) for bad input before anything is written, and when no
    frame holds a label the depth confirms.
    """
    cfg = settings if isinstance(settings, AdaptConfig) else AdaptConfig.from_mapping(settings)
    weights, mesh, out = require_file(weights, "--weights"), require_file(mesh, "--mesh"), Path(out)
    if max_frames is not None and int(max_frames) < 1:
        raise ConfigError(f"--max-frames must be at least 1, got {max_frames}")
    predictor = DopePredictor(weights, mesh=mesh, mesh_units=mesh_units, options=cfg.infer.given())
    if len(predictor.objects) != 1:
        raise ConfigError(f"{weights}: a model of {len(predictor.objects)} objects; adapt fine-tunes one-object models")
    synth = _check_synthetic([Path(s) for s in synthetic]) if synthetic else recorded_synthetic(weights)
    if cfg.finetune.synthetic_ratio > 0 and not synth:
        raise ConfigError("--synthetic: give the synthetic frames the model was trained on (its checkpoint records "
                          "none that exist here), or --set finetune.synthetic_ratio=0")
    job = {"weights": str(weights.resolve()), "mesh": str(mesh.resolve()), "mesh_units": mesh_units,
           "inputs": [str(i) for i in inputs], "max_frames": max_frames, "synthetic": [str(s) for s in synth],
           "settings": cfg.to_dict()}
    store = FrameStore(out / "frames")
    source = None if store.complete else open_unlabelled(
        list(map(str, inputs)), camera, Path(depth) if depth is not None else None, depth_scale_mm,
        image_topic, depth_topic, camera_info_topic, note)
    output_dir(out)
    changed = settings_changed(out / "job.json", json.loads(json.dumps(job)))
    if changed:
        if source is not None:
            source.close()
        raise ConfigError(f"{out}: the folder of another adapt job (it differs in {', '.join(changed[:3])}); "
                          "give a new --out, or the same inputs and settings to resume it")
    if source is not None:
        _read_frames(source, store, max_frames, progress)
    note(f"{len(store)} frame(s) in {store.folder}")
    result = AdaptResult("completed", None)
    model = weights
    rounds = cfg.finetune.rounds
    for r in range(1, rounds + 1):
        folder = out / f"round_{r}"
        labels = folder / "labels"
        if (labels / "summary.json").is_file():
            counts = LabelCounts(**json.loads((labels / "summary.json").read_text())["counts"])
        else:
            p = predictor if r == 1 else DopePredictor(model, mesh=mesh, mesh_units=mesh_units,
                                                       options=cfg.infer.given())
            counts = _label_round(store, p, cfg, labels, out / f"preview_round_{r}.png" if preview else None,
                                  {"model": str(model), "round": r}, progress,
                                  lambda m=model: _seed_predictor(m, mesh, mesh_units, cfg))
        note(f"round {r}: {counts.detected_kept} detected and {counts.carried_kept} carried label(s) kept, "
             f"{counts.detected_rejected + counts.carried_rejected} rejected; {counts.labelled_frames} of "
             f"{counts.frames} frames labelled, {counts.filled_frames} of the {counts.missed_frames} the model missed")
        if not counts.labelled_frames:
            raise DopeHopeError(f"round {r}: the depth confirms no label in the {counts.frames} frame(s) "
                                f"({_common_reason(labels)}); see {labels / 'labels.jsonl'}")
        mix = folder / "mix"
        n_synth = synthetic_mix(mix, synth, counts.labelled_frames, cfg.finetune, r) if synth else 0
        data = [labels] + ([mix] if n_synth else [])
        trained = finetune_round(model, data, counts.labelled_frames + n_synth, folder / "train", mesh, mesh_units, cfg.finetune,
                                 cfg.finetune.time_budget_min / rounds, progress)
        result.rounds.append({"round": r, "counts": counts.__dict__, "synthetic": n_synth, "training": trained})
        if trained.get("status") not in FINISHED:
            result.status = str(trained.get("status"))
            return result
        model = Path(trained["weights"])
        note(f"round {r}: trained ({trained.get('status')}, step {trained.get('step')}) -> {model}")
    result.weights = record_adaptation(model, out / ADAPTED_NAME, {
        "from": str(weights), "frames": job["inputs"], "frame_count": len(store), "rounds": result.rounds,
        "synthetic": job["synthetic"], "settings": job["settings"]})
    return result


def _common_reason(labels: Path) -> str:
    """The commonest rejection reason of a round's written records ("no detection" when none)."""
    path = labels / "labels.jsonl"
    reasons = Counter(rec["reason"].split("< ")[-1].split("> ")[-1].split(" ")[0]  # the setting it failed
                      for line in path.read_text().splitlines() for rec in json.loads(line)["rejected"]) \
        if path.is_file() else Counter()
    if not reasons:
        return "the model detected nothing"
    what, n = reasons.most_common(1)[0]
    return f"commonest rejection: {what} ({n} pose(s))"
