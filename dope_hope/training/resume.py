"""What a training checkpoint records of its run and how a resumed run continues from it:
:class:`CheckpointStore` (``last.pt`` / ``best.pt`` written from the state the trainer hands it:
model, optimizer, scheduler, step, epoch and the run's bookkeeping), :class:`RunProgress` (the
counters a checkpoint records and a resumed run picks up again, so that an interrupted CPU run
ends with the same weights as an uninterrupted one), :func:`job_record` (the job's data and
objects, as recorded), :func:`resumed_job` (what ``--resume`` fills in of a job from the
checkpoint) and :func:`check_resume_flags` (what a resumed run cannot honour: refused).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torch import nn

from dope_hope.errors import ConfigError
from dope_hope.io.models_dir import check_run_object
from dope_hope.model.checkpoint import TrainingState, load_checkpoint, save_checkpoint
from dope_hope.training.objects import object_mesh_paths
from dope_hope.training.settings import TrainConfig, TrainJob

#: The trainer's logger: these lines are the trainer's, under its name.
log = logging.getLogger("dope_hope.training.trainer")


@dataclass
class RunProgress:
    """Where a run stands beyond its weights: what a checkpoint's ``extra`` records of the
    loop and a resumed run continues from.

    Attributes:
        batch_in_epoch: batches of the current epoch done.
        best_acc: the best validation keypoint accuracy so far (-1: none yet).
        val_done_epoch: the last epoch validated (-1: none).
        last_val: the last validation's figures.
        loss_window: the loss sum and steps of the next train row of metrics.csv.
        metrics_rows: rows of metrics.csv written.
    """

    batch_in_epoch: int = 0
    best_acc: float = -1.0
    val_done_epoch: int = -1
    last_val: dict[str, Any] = field(default_factory=dict)
    loss_window: list[float] = field(default_factory=lambda: [0.0, 0])
    metrics_rows: int = 0

    @classmethod
    def from_extra(cls, extra: dict[str, Any], epoch: int, steps_per_epoch: int) -> RunProgress:
        """The progress a checkpoint's ``extra`` records of a run stopped in ``epoch`` (a run
        stopped mid-epoch validates again when that epoch ends)."""
        progress = cls(batch_in_epoch=int(extra.get("batch_in_epoch", 0)),
                       best_acc=float(extra.get("best_acc", -1.0)),
                       val_done_epoch=int(extra.get("val_done_epoch", -1)),
                       last_val=dict(extra.get("val") or {}), metrics_rows=int(extra.get("metrics_rows", 0)))
        if progress.batch_in_epoch < steps_per_epoch and progress.val_done_epoch == epoch:
            progress.val_done_epoch = -1  # stopped mid-epoch: validate again when the epoch ends
        window = extra.get("loss_window")
        if isinstance(window, (list, tuple)) and len(window) == 2:
            progress.loss_window = [float(window[0]), int(window[1])]
        return progress

    def extra(self, metrics_rows: int) -> dict[str, Any]:
        """The checkpoint ``extra`` entries of the progress (``metrics_rows``: the rows written now)."""
        return {"batch_in_epoch": self.batch_in_epoch, "best_acc": self.best_acc,
                "val_done_epoch": self.val_done_epoch, "loss_window": list(self.loss_window),
                "metrics_rows": metrics_rows,
                "val": {k: v for k, v in self.last_val.items() if isinstance(v, (int, float))}}


def job_record(job: TrainJob, several: bool) -> dict[str, Any]:
    """The job a checkpoint records (its data, objects and meshes; ``several``: a run of
    several objects, whose classes, meshes and units are listed): what ``--resume`` fills in."""
    return {"data": [str(p) for p in job.data], "val": [str(p) for p in job.val],
            "object": job.object_name, "mesh": str(job.mesh) if job.mesh else None,
            **({"objects": job.class_names, "meshes": object_mesh_paths(job),
                "units": dict(job.units)} if several else {}),
            "symmetries": str(job.symmetries) if job.symmetries else None,
            "init": str(job.init_weights) if job.init_weights else None}


class CheckpointStore:
    """A run's checkpoints in its output folder (``out``), each written atomically from the
    state it is handed (by rank 0 alone: the trainer's call)."""

    def __init__(self, out: Path):
        self.out = Path(out)

    def save(self, name: str, model: nn.Module, recipe: TrainConfig, object_entry: Any,
             state: TrainingState) -> Path:
        """Write ``out/name``: the weights, every key of the ``recipe`` over the defaults (the
        file says how it was trained), the object entry and the training ``state``; returns
        its path."""
        return save_checkpoint(self.out / name, model, recipe.to_dict(), object_entry, state)


def resumed_job(job: TrainJob) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """(checkpoint or None, the recipe it records or None): with ``job.resume`` the data,
    objects and meshes the checkpoint records fill what the job leaves out."""
    ck = None
    saved_config: dict[str, Any] | None = None
    if job.resume is not None:
        ck = load_checkpoint(job.resume)
        saved_config = ck.get("config") or None
        saved_job = checkpoint_extra(ck).get("job") or {}
        check_resume_flags(job, saved_job)
        if not job.data:
            job.data = [Path(p) for p in saved_job.get("data", [])]
            job.val = job.val or [Path(p) for p in saved_job.get("val", [])]
        if not job.object_name:
            job.object_name = str(saved_job.get("object", ""))
            job.objects = job.objects or list(saved_job.get("objects") or [])
            job.meshes = job.meshes or {k: Path(v) for k, v in (saved_job.get("meshes") or {}).items() if v}
            job.units = job.units or dict(saved_job.get("units") or {})
        if job.mesh is None and saved_job.get("mesh"):
            job.mesh = Path(saved_job["mesh"])
        if job.symmetries is None and saved_job.get("symmetries"):
            job.symmetries = Path(saved_job["symmetries"])
        if not job.data or not job.object_name:
            raise ConfigError(f"{job.resume} does not record its data folders / object; pass --data and --object")
    return ck, saved_config


def check_resume_flags(job: TrainJob, saved_job: dict[str, Any]) -> None:
    """ConfigError naming the flag for what a run continued from ``job.resume`` cannot honour
    (``saved_job``: the job its checkpoint records): other objects than its own (``--object``:
    the network's map groups are the checkpoint's objects, in its order),
    ``--backbone-weights`` (the checkpoint's weights replace them) and ``--mesh NAME=PATH``
    naming no object of the run."""
    saved = [str(n) for n in saved_job.get("objects") or ([saved_job["object"]] if saved_job.get("object") else [])]
    given = job.class_names if job.object_name else []
    if given and saved and [n.lower() for n in given] != [n.lower() for n in saved]:
        raise ConfigError(f"--object {' '.join(given)}: --resume continues {job.resume}, a run of "
                          f"{', '.join(saved)}, whose objects it cannot change; drop --object, or start a new "
                          "run (another --out)")
    if job.backbone_weights is not None:
        raise ConfigError(f"--backbone-weights {job.backbone_weights}: --resume continues {job.resume} with its "
                          "own weights; give one of them")
    if job.mesh_name is not None and saved:
        check_run_object(job.mesh_name, saved, "--mesh", f"{job.mesh_name}={job.mesh}")


def checkpoint_extra(ck: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's ``extra`` dict (the run's state beyond model and optimizer), {} when none."""
    extra = ck.get("extra")
    return extra if isinstance(extra, dict) else {}
