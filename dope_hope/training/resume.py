"""What a training checkpoint records of its run and how a resumed run continues from it:
:meth:`RunCheckpoints.save` (model, optimizer, scheduler, step, epoch, the batch position, the
time budget's plans and time used, the partial loss window, the job's data and objects),
:meth:`RunCheckpoints._restore` (a resumed run picks all of it up again, so that an
interrupted CPU run ends with the same weights as an uninterrupted one) and
:func:`resumed_job` (what ``--resume`` fills in of a job from the checkpoint) and
:func:`check_resume_flags` (what a resumed run cannot honour: refused).

:class:`RunCheckpoints` is a part of :class:`~dope_hope.training.trainer.Trainer` (it reads
and sets the trainer's counters).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from dope_hope.errors import ConfigError
from dope_hope.io.models_dir import check_run_object
from dope_hope.model.checkpoint import (
    TrainingState,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from dope_hope.training.objects import object_mesh_paths
from dope_hope.training.schedule import LrLambda
from dope_hope.training.settings import TrainConfig, TrainJob

#: The trainer's logger: these lines are the trainer's, under its name.
log = logging.getLogger("dope_hope.training.trainer")


class RunCheckpoints:
    """The trainer's checkpoints: ``last.pt`` / ``best.pt`` written, a resumed run restored."""

    def _restore(self, ck: dict[str, Any], saved_ts: dict[str, Any]) -> None:
        """Continue from checkpoint ``ck``; ``saved_ts``: its ``train`` settings (a length or
        budget given now that differs wins, said in one line)."""
        self.model.load_state_dict(ck["model"])
        if ck.get("optimizer") is not None:
            self.optimizer.load_state_dict(ck["optimizer"])
        if ck.get("scheduler") is not None:
            self.scheduler.load_state_dict(ck["scheduler"])
        self.step = int(ck.get("step", 0))
        self.epoch = int(ck.get("epoch", 0))
        extra = checkpoint_extra(ck)
        self.batch_in_epoch = int(extra.get("batch_in_epoch", 0))
        self.best_acc = float(extra.get("best_acc", -1.0))
        self.val_done_epoch = int(extra.get("val_done_epoch", -1))
        if self.batch_in_epoch < self.steps_per_epoch and self.val_done_epoch == self.epoch:
            self.val_done_epoch = -1  # stopped mid-epoch: validate again when the epoch ends
        self._time_used_before = float(extra.get("time_used_s", 0.0))
        self._other_before = float(extra.get("other_s", 0.0))
        self._val_seconds = float(extra.get("last_val_s", 0.0))
        self._val_steps = [float(v) for v in extra.get("val_steps") or []]
        self._metrics_rows = int(extra.get("metrics_rows", 0))
        self.last_val = dict(extra.get("val") or {})
        window = extra.get("loss_window")
        if isinstance(window, (list, tuple)) and len(window) == 2:
            self.loss_window = [float(window[0]), int(window[1])]
        if ck.get("rng"):
            restore_rng_state(ck["rng"])
        if self.dist.main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", self.job.resume, self.step, self.epoch, self.batch_in_epoch)
        self._restore_length(extra, saved_ts)

    def _restore_length(self, extra: dict[str, Any], saved_ts: dict[str, Any]) -> None:
        """The resumed run's end: the checkpoint's plans when its length and budget are kept;
        a length (``steps``, ``epochs``) or budget given now that differs wins, at once (one
        line says so) and the learning rate falls from where it is to the new end."""
        plans = extra.get("plans")
        if plans is None and extra.get("planned_steps") is not None and self.budget is not None:
            self.total_steps = min(self._nominal_total, int(extra["planned_steps"]))  # one fixed plan: measured again
        keys = ("steps", "epochs", "time_limit_min")
        changed = [k for k in keys if self.ts[k] != saved_ts.get(k)]
        if self.budget is not None and plans and "time_limit_min" not in changed:
            self.budget.plans = [dict(p) for p in plans]
            self.total_steps = min(self._nominal_total, int(plans[-1]["budget_end"]))
        if self.budget is not None and plans and changed:  # planned again at once, at the last plan's speed
            self.budget.plans = [dict(p) for p in plans]
            end = self._plan_now("length or budget changed at resume") if self.dist.main else None
            self._set_end(self._broadcast_end(end))
        elif changed and self.budget is None:
            self.total_steps = self._nominal_total
        if changed and self.ts["schedule"] in LrLambda.REPLANNED and not self.budget_sets_horizon:
            self.lr_lambda.replan(self.step, max(self.step + 1, self.total_steps))
        if changed and self.dist.main:
            now = ", ".join(f"train.{k} {self.ts[k]}" for k in changed)
            before = ", ".join(f"{saved_ts.get(k)}" for k in changed)
            tail = (f", or earlier when the {self.ts['time_limit_min']:g}-min time budget is spent"
                    if self.budget is not None and self.total_steps >= self._nominal_total else "")
            log.warning("resume: %s given now win(s) over the checkpoint's %s: the run ends at step %d%s",
                        now, before, self.total_steps, tail)

    def save(self, name: str) -> Path:
        """Write ``out/name`` atomically (rank 0 only); returns its path."""
        path = self.out / name
        if not self.dist.main:
            return path
        extra = {
            "batch_in_epoch": self.batch_in_epoch, "best_acc": self.best_acc, "val_done_epoch": self.val_done_epoch,
            "time_used_s": self.budget_used(), "other_s": self.other_time(),
            "last_val_s": self._val_seconds, "val_steps": self._val_steps[-3:], "size_source": self.size_source,
            "planned_steps": self.planned_steps, "plans": self.budget.plans if self.budget is not None else None,
            "loss_window": list(self.loss_window),
            "metrics_rows": self.metrics.rows if self.metrics is not None else self._metrics_rows,
            "val": {k: v for k, v in self.last_val.items() if isinstance(v, (int, float))},
            "world_size": self.dist.world_size,
            "job": {"data": [str(p) for p in self.job.data], "val": [str(p) for p in self.job.val],
                    "object": self.job.object_name, "mesh": str(self.job.mesh) if self.job.mesh else None,
                    **({"objects": self.job.class_names, "meshes": object_mesh_paths(self.job),
                        "units": dict(self.job.units)} if len(self.objects) > 1 else {}),
                    "symmetries": str(self.job.symmetries) if self.job.symmetries else None,
                    "init": str(self.job.init_weights) if self.job.init_weights else None},
        }
        # every key of the recipe, over the defaults: the file says how it was trained
        recipe = TrainConfig.from_mapping(self.config).to_dict()
        save_checkpoint(path, self.model, recipe, self.object,
                        TrainingState(self.optimizer, self.scheduler, self.step, self.epoch, extra))
        return path


def resumed_job(job: TrainJob, config: dict[str, Any]) -> tuple[dict[str, Any] | None, dict[str, Any], dict[str, Any]]:
    """(checkpoint or None, the config to build from, the checkpoint's own config or {}): with
    ``job.resume`` the checkpoint's config and the data, objects and meshes it records fill
    what the job leaves out."""
    ck = None
    saved_config: dict[str, Any] = {}
    if job.resume is not None:
        ck = load_checkpoint(job.resume)
        config = saved_config = ck.get("config") or config
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
    return ck, config, saved_config


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
