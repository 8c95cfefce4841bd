"""The training loop: data, loss, optimizer + schedule, validation, checkpoints, resume, DDP.

:func:`train` runs one job described by :class:`~dope_hope.training.settings.TrainJob` and a
full config (sections ``model``, ``input``, ``targets``, ``train``, ``augment``; see
``dope_hope/configs/lite.yaml``).

* Optimizer Adam/AdamW; schedule in :mod:`~dope_hope.training.schedule`; loss in
  :mod:`~dope_hope.training.loss`.
* Validation after every epoch on held-out frames (``--val`` or a seeded split): loss and the
  keypoint accuracy (:mod:`~dope_hope.training.validation`).
* Determinism and resume: the data order is a function of (seed, epoch) (EpochSampler), every
  item of (seed, epoch, index); a checkpoint records model, optimizer, scheduler, step, epoch,
  the batch position inside the epoch and the python/numpy/torch RNG states, so an interrupted
  CPU run resumed from its checkpoint ends with the same weights as an uninterrupted one.
* Time limit: the budget belongs to the run. After the batches the loader fetched ahead and
  ``horizon_estimate_after`` more steps (or the first epoch, if shorter) the measured speed
  turns the budget left into the step the run ends at (``planned_steps``; the cosine spans it
  unless steps were given). The plan and the time used are saved in every checkpoint, so a
  resumed run ends at the same step with the same weights; before the plan the run stops when
  the time (of every process so far) runs out.
* Ctrl-C / SIGTERM: finish the current step, write ``last.pt``, return ``interrupted``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import random
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from dope_hope.config import merge
from dope_hope.devices import native_bf16
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import KEYPOINT_ORDER
from dope_hope.model.checkpoint import (
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from dope_hope.training.distributed import init_distributed
from dope_hope.training.loss import optimizer_step, stage_loss
from dope_hope.training.metrics_log import MetricsLog
from dope_hope.training.objects import object_mesh_paths, relabel_objects
from dope_hope.training.schedule import LrLambda
from dope_hope.training.settings import (
    TrainJob,
    input_hw,
    check_config_keys,
    train_settings,
)
from dope_hope.training.validation import object_hits

log = logging.getLogger(__name__)

#: Batches each DataLoader worker fetches ahead (PyTorch's default, passed explicitly because the
#: time-budget plan starts its clock once those are used up).
LOADER_PREFETCH = 2


# =============================================================================== trainer
class Trainer:
    """One training job; :meth:`run` returns a summary dict (see :func:`train`)."""

    def __init__(self, job: TrainJob, config: dict[str, Any]):
        from dope_hope.model.network import build_model
        from dope_hope.training.augment import AugmentParams
        from dope_hope.training.dataset import DopeDataset, EpochSampler, split_records
        from dope_hope.training.objects import check_class_names, with_num_objects
        from dope_hope.training.sources import scan_training_data

        self.job = job
        self.dist, self.device = init_distributed(job.device)
        if not self.dist.main:  # rank 0 alone reports (skipped files, progress, results)
            logging.getLogger("dope_hope").setLevel(logging.ERROR)
        self.out = Path(job.out)
        self.stop_reason: str | None = None
        self._signal_count = 0

        ck = None
        if job.resume is not None:
            ck = load_checkpoint(job.resume)
            config = ck.get("config") or config
            saved_job = _extra(ck).get("job") or {}
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
        config = merge(config, job.overrides)
        check_config_keys(config)
        check_class_names(job.class_names)
        config = with_num_objects(config, len(job.class_names))
        self.config = config
        self.ts = train_settings(config)
        ts = self.ts
        if ts["threads"]:
            torch.set_num_threads(int(ts["threads"]))
        self.seed = int(ts["seed"])
        if ck is None:
            random.seed(self.seed)
            np.random.seed(self.seed % (2**32))
            torch.manual_seed(self.seed)

        # ---- data
        hw = input_hw(config)
        tcfg = config.get("targets") or {}
        self.model = build_model(config)  # before the data: stride comes from the model
        if job.backbone_weights is not None:
            from dope_hope.model.network import load_backbone_weights
            load_backbone_weights(self.model, job.backbone_weights)
        stride = int(self.model.stride)
        scan = dict(min_visibility=float(ts["min_visibility"]), include_empty=bool(ts["include_empty_frames"]),
                    progress=job.progress and self.dist.main)
        records, _ = scan_training_data(job.data, job.class_names, KEYPOINT_ORDER, **scan)
        if not any(len(r.keypoints) for r in records):
            folders = ", ".join(str(p) for p in job.data)
            raise InputFileError(folders, f"no annotated instance of class {' / '.join(job.class_names)!r}")
        if job.val:
            val_records, _ = scan_training_data(job.val, job.class_names, KEYPOINT_ORDER, **scan)
            if not val_records:
                raise InputFileError(", ".join(str(p) for p in job.val), "no readable validation frames")
        else:
            records, val_records = split_records(records, float(ts["val_fraction"]), self.seed)
        if ck is None:  # after the data checks: a bad folder or class is the only line printed
            if job.init_weights is not None:
                load_init_weights(self.model, job.init_weights)
            if job.init_reason:
                log.info("start: %s", job.init_reason)
        self._set_objects(records)
        (records, val_records), self.symmetry_permutations, lines = relabel_objects(
            tcfg.get("symmetry", "none"), job, self.objects, [records, val_records])
        for line in lines:
            log.info("symmetry-aware labels: %s", line)
        common = dict(input_hw=hw, stride=stride, sigma=float(tcfg.get("sigma", 2.0)),
                      radius=float(tcfg.get("radius", 1.0)), seed=self.seed, max_instances=int(ts["max_instances"]),
                      num_objects=len(self.objects))
        self.train_set = DopeDataset(records, augment=AugmentParams.from_config(config.get("augment")), **common)
        self.val_set = DopeDataset(val_records, augment=AugmentParams(enabled=False), **common)
        self.batch_size = int(ts["batch_size"])
        if len(self.train_set) < self.batch_size * self.dist.world_size:
            raise ConfigError(f"{len(self.train_set)} training frames are fewer than one batch "
                              f"({self.batch_size} x {self.dist.world_size} processes); lower --batch-size")
        self.sampler = EpochSampler(len(self.train_set), self.seed, True, self.dist.rank, self.dist.world_size)
        self.val_sampler = EpochSampler(len(self.val_set), self.seed, False, self.dist.rank, self.dist.world_size)
        self.steps_per_epoch = len(self.sampler) // self.batch_size

        # ---- model, optimizer, schedule
        self.model.to(self.device)
        self.cuda = self.device.type == "cuda"
        self.channels_last = bool(ts["channels_last"])
        self.amp = bool(ts["amp"]) and native_bf16(self.device.type)
        if self.dist.main and bool(ts["amp"]) != self.amp:
            log.info("train.amp: float32 (this %s has no native bfloat16)", self.device.type.upper())
        if self.channels_last:
            self.model.to(memory_format=torch.channels_last)
        opt_cls = torch.optim.AdamW if ts["optimizer"] == "adamw" else torch.optim.Adam
        self.optimizer = opt_cls(self.model.parameters(), lr=float(ts["lr"]),
                                 weight_decay=float(ts["weight_decay"]), betas=tuple(ts["betas"]))
        self.epochs = int(ts["epochs"])
        self.total_steps = int(ts["steps"]) if ts["steps"] else self.epochs * self.steps_per_epoch
        if ts["steps"]:
            self.epochs = math.ceil(self.total_steps / self.steps_per_epoch)
        self.time_limit_s = float(ts["time_limit_min"]) * 60.0 if ts["time_limit_min"] else None
        self._nominal_total = self.total_steps
        #: Under a time limit: the step the run ends at, fixed once from the measured speed
        #: (see _maybe_plan) and kept in the checkpoint, so that a resumed run ends where an
        #: uninterrupted one does. None until planned.
        self.planned_steps: int | None = None
        # Under a time limit the schedule spans the planned steps, unless steps were given.
        self.estimate_horizon = self.time_limit_s is not None and not ts["steps"]
        self.lr_lambda = LrLambda(ts["schedule"], self.total_steps, int(ts["warmup_steps"]), float(ts["min_lr_factor"]),
                                  int(ts["step_epochs"]) * self.steps_per_epoch, float(ts["step_gamma"]))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, self.lr_lambda)

        self.step = 0
        self.epoch = 0
        self.batch_in_epoch = 0
        self.best_acc = -1.0
        self.last_val: dict[str, Any] = {}
        self.val_done_epoch = -1
        self._time_used_before = 0.0
        self._metrics_rows = 0
        self.metrics: MetricsLog | None = None
        if ck is not None:
            self._restore(ck)
        self.ddp_model: nn.Module = self.model
        if self.dist.active:
            self.ddp_model = nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.cuda else None)

    def _set_objects(self, records: list[Any]) -> None:
        """The run's objects (:mod:`dope_hope.training.objects`): ``objects``, the checkpoint's
        ``object`` (one entry, or the list of several) and where the sizes came from."""
        from dope_hope.training.objects import checkpoint_objects, run_objects

        self.objects = run_objects(self.job, records)
        self.object = checkpoint_objects(self.objects)
        self.size_source = self.objects[0].size_source if len(self.objects) == 1 else \
            {o.name: o.size_source for o in self.objects}

    # ------------------------------------------------------------------ checkpoints
    def _restore(self, ck: dict[str, Any]) -> None:
        self.model.load_state_dict(ck["model"])
        if ck.get("optimizer") is not None:
            self.optimizer.load_state_dict(ck["optimizer"])
        if ck.get("scheduler") is not None:
            self.scheduler.load_state_dict(ck["scheduler"])
        self.step = int(ck.get("step", 0))
        self.epoch = int(ck.get("epoch", 0))
        extra = _extra(ck)
        self.batch_in_epoch = int(extra.get("batch_in_epoch", 0))
        self.best_acc = float(extra.get("best_acc", -1.0))
        self.val_done_epoch = int(extra.get("val_done_epoch", -1))
        if self.batch_in_epoch < self.steps_per_epoch and self.val_done_epoch == self.epoch:
            self.val_done_epoch = -1  # stopped mid-epoch: validate again when the epoch ends
        self._time_used_before = float(extra.get("time_used_s", 0.0))
        self._metrics_rows = int(extra.get("metrics_rows", 0))
        self.last_val = dict(extra.get("val") or {})
        plan = extra.get("planned_steps")
        if plan is not None and self.time_limit_s is not None and extra.get("plan_budget_min") == self.ts["time_limit_min"]:
            self.planned_steps = int(plan)  # the same budget: the same end
            self.total_steps = min(self.total_steps, self.planned_steps)
        elif self.estimate_horizon:
            self.lr_lambda.horizon = max(1, self.total_steps)  # planned again (budget changed)
        if ck.get("rng"):
            restore_rng_state(ck["rng"])
        # the scheduler's state restored lr_lambda's attributes; steps / epochs given now win
        if not self.estimate_horizon:
            self.lr_lambda.horizon = max(1, self.total_steps)
        if self.dist.main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", self.job.resume, self.step, self.epoch, self.batch_in_epoch)

    def save(self, name: str) -> Path:
        """Write ``out/name`` atomically (rank 0 only); returns its path."""
        path = self.out / name
        if not self.dist.main:
            return path
        extra = {
            "batch_in_epoch": self.batch_in_epoch, "best_acc": self.best_acc, "val_done_epoch": self.val_done_epoch,
            "time_used_s": self.budget_used(), "size_source": self.size_source,
            "planned_steps": self.planned_steps, "plan_budget_min": self.ts["time_limit_min"],
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
        save_checkpoint(path, self.model, self.config, self.object, optimizer=self.optimizer,
                        scheduler=self.scheduler, step=self.step, epoch=self.epoch, extra=extra)
        return path

    # ------------------------------------------------------------------ control
    def elapsed(self) -> float:
        """Seconds this process has run the loop."""
        return time.monotonic() - self._t0

    def budget_used(self) -> float:
        """Seconds of the time budget used: earlier processes' (up to their last checkpoint)
        plus this one's."""
        return self._time_used_before + self.elapsed()

    def request_stop(self, reason: str = "interrupted") -> None:
        """Stop after the current step (what Ctrl-C / SIGTERM do)."""
        self.stop_reason = self.stop_reason or reason

    def _on_signal(self, signum: int, frame: Any) -> None:
        self._signal_count += 1
        if self._signal_count > 1:
            raise KeyboardInterrupt
        self.request_stop("interrupted" if signum == signal.SIGINT else "terminated")

    def _agree_stop(self) -> bool:
        """True on every rank when any rank wants to stop (time limit, signal)."""
        # Before the plan (the first steps of a run): the final validation must fit in the
        # budget too, stop when it would not. After it, the planned step count ends the run.
        if (self.time_limit_s is not None and self.planned_steps is None and self.stop_reason is None
                and self.budget_used() + self._val_seconds >= self.time_limit_s):
            self.stop_reason = "time_limit"
        if not self.dist.active:
            return self.stop_reason is not None
        reasons = (None, "time_limit", "terminated", "interrupted")
        t = torch.tensor([reasons.index(self.stop_reason)], dtype=torch.int32, device=self.device if self.cuda else "cpu")
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        self.stop_reason = reasons[int(t.item())]
        return self.stop_reason is not None

    def _maybe_plan(self, epoch_end: bool = False) -> None:
        """Time-limited run: once the speed is known (``horizon_estimate_after`` steps of this
        process, or the end of an epoch), turn the budget left into the step the run ends at.

        The plan is made once, broadcast to every rank and saved in the checkpoint: from then
        on the run is one of a fixed number of steps (the cosine spans them), so an
        interrupted and resumed run ends at the same step with the same weights.
        """
        if self.time_limit_s is None or self.planned_steps is not None:
            return
        n = self._steps_this_run
        # The clock starts after start-up (step 1) and again once the batches the loader fetched
        # ahead while the run started are used up: they come for free, and counting them makes a
        # loader-bound run look faster than it is (it would overrun its budget).
        steady = 1 + (int(self.ts["workers"]) * LOADER_PREFETCH)
        if n in (1, steady) and not epoch_end:
            self._plan_t1, self._plan_val1, self._plan_n1 = time.monotonic(), self._val_time_run, n
            return
        if (self._plan_t1 is None or n <= self._plan_n1
                or (n < steady + int(self.ts["horizon_estimate_after"]) - 1 and not epoch_end)):
            return
        per_step = max(1e-9, (time.monotonic() - self._plan_t1 - (self._val_time_run - self._plan_val1))
                       / (n - self._plan_n1))
        val_batches = math.ceil(len(self.val_set) / max(1, int(self.ts["val_batch_size"] or self.batch_size)))
        # No validation measured yet: a batch costs about a training step per unit of image area
        # (forward + decoding of whole frames vs forward + backward of the training crops).
        h, w = input_hw(self.config)
        crop = self.train_set.augment.crop or (h, w)
        val_cost = self._val_seconds or per_step * val_batches * max(1.0, h * w / (crop[0] * crop[1]))
        every = int(self.ts["val_every"]) * self.steps_per_epoch  # steps between validations
        remaining = self.time_limit_s - self.budget_used() - val_cost  # the final validation fits
        steps = max(0.0, remaining / (per_step + (val_cost / every if every > 0 else 0.0)))
        planned = min(self._nominal_total, max(self.step, self.step + int(steps)))
        if self.dist.active:
            t = torch.tensor([planned], dtype=torch.int64, device=self.device if self.cuda else "cpu")
            dist.broadcast(t, 0)
            planned = int(t.item())
        self.planned_steps = planned
        self.total_steps = planned
        if self.estimate_horizon:
            self.lr_lambda.horizon = max(self.step + 1, planned)
        if self.dist.main:
            log.info("time budget %.3g min: the run ends at step %d (%.3f s per step, %.1f s of the "
                     "budget used by step %d)", self.time_limit_s / 60.0, planned, per_step,
                     self.budget_used(), self.step)

    def _loader(self, dataset: Any, sampler: Any, batch_size: int, drop_last: bool) -> torch.utils.data.DataLoader:
        from dope_hope.training.dataset import collate

        workers = int(self.ts["workers"])
        return torch.utils.data.DataLoader(
            dataset, batch_size=batch_size, sampler=sampler, num_workers=workers, collate_fn=collate,
            drop_last=drop_last, pin_memory=self.cuda, persistent_workers=False,
            prefetch_factor=LOADER_PREFETCH if workers > 0 else None,
            multiprocessing_context="fork" if workers > 0 and os.name == "posix" else None)

    def _report_bad(self, files: list[str]) -> None:
        from dope_hope.training.dataset import report_bad_file

        for f in files:
            report_bad_file(f, "unreadable image, replaced by another frame")

    # ------------------------------------------------------------------ steps
    def _to_device(self, x: torch.Tensor, image: bool = False) -> torch.Tensor:
        x = x.to(self.device, non_blocking=True)
        if image and self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def train_step(self, batch: dict[str, Any]) -> float:
        images = self._to_device(batch["image"], image=True)
        belief, affinity = self._to_device(batch["belief"]), self._to_device(batch["affinity"])
        loss = optimizer_step(self.ddp_model, self.optimizer, images, belief, affinity, amp=self.amp,
                              belief_weight=float(self.ts["belief_weight"]),
                              affinity_weight=float(self.ts["affinity_weight"]), grad_clip=self.ts["grad_clip"],
                              foreground_weight=float(self.ts["foreground_weight"]))
        self.scheduler.step()
        return loss

    @torch.no_grad()
    def validate(self) -> dict[str, Any]:
        """Loss and keypoint accuracy on the validation frames (all ranks; summed across)."""
        self.model.eval()
        stride = int(self.model.stride)
        radius = float(self.ts["val_radius_px"])
        thr = float(self.ts["val_peak_threshold"])
        n_obj = len(self.objects)
        # loss*n, n, then per object: found, visible, found_dec, visible_dec
        sums = torch.zeros(2 + 4 * n_obj, dtype=torch.float64)
        self.val_sampler.set_epoch(0)
        bs = int(self.ts["val_batch_size"] or self.batch_size)
        for batch in self._loader(self.val_set, self.val_sampler, bs, drop_last=False):
            self._report_bad(batch["bad_files"])
            images = self._to_device(batch["image"], image=True)
            outputs = self.model(images)  # float32, as inference runs it (train.amp is for training)
            n = images.shape[0]
            loss = stage_loss(outputs, self._to_device(batch["belief"]), self._to_device(batch["affinity"]),
                              float(self.ts["belief_weight"]), float(self.ts["affinity_weight"]),
                              float(self.ts["foreground_weight"]))
            sums[0] += float(loss) * n
            sums[1] += n
            belief = outputs[-1][0].float().cpu().numpy()
            affinity = outputs[-1][1].float().cpu().numpy()
            gt = batch["keypoints"].numpy().astype(np.float64)
            classes = batch["classes"].numpy()
            for i in range(n):
                hits = object_hits(belief[i], affinity[i], gt[i], classes[i], n_obj, stride, radius, thr)
                sums[2:] += torch.from_numpy(hits.reshape(-1).astype(np.float64))
        if self.dist.active:
            t = sums.to(self.device if self.cuda else "cpu")
            dist.all_reduce(t)
            sums = t.cpu()
        s = sums.tolist()
        per = sums[2:].reshape(n_obj, 4).sum(0).tolist()
        return {
            "val_loss": s[0] / max(s[1], 1),
            "val_kp_acc": per[0] / per[1] if per[1] else float("nan"),
            "val_kp_acc_decoded": per[2] / per[3] if per[3] else float("nan"),
            "val_frames": int(s[1]), "val_keypoints": int(per[1]), "val_radius_px": radius,
            **per_object_accuracy([o.name for o in self.objects], sums[2:].reshape(n_obj, 4)),
        }

    def _end_of_epoch(self) -> None:
        every = int(self.ts["val_every"])
        last_epoch = self.epoch + 1 >= self.epochs or self.step >= self.total_steps or self.stop_reason is not None
        if (every > 0 and ((self.epoch + 1) % every == 0 or last_epoch)) or (every > 0 and self.stop_reason == "time_limit"):
            t0 = time.monotonic()
            self.last_val = self.validate()
            self._val_seconds = time.monotonic() - t0
            self._val_time_run += self._val_seconds
            self.val_done_epoch = self.epoch
            if self.dist.main:
                self.metrics.write("val", step=self.step, epoch=self.epoch, time_s=round(self._time_used_before + self.elapsed(), 2),
                                   **{k: v for k, v in self.last_val.items()
                                      if k in ("val_loss", "val_kp_acc", "val_kp_acc_decoded") or "/" in k})
                log.info("epoch %d step %d: val loss %.5f, keypoints within %g px %.3f (peaks) %.3f (decoded)",
                         self.epoch, self.step, self.last_val["val_loss"], self.last_val["val_radius_px"],
                         self.last_val["val_kp_acc"], self.last_val["val_kp_acc_decoded"])
                acc = self._primary_acc()
                if acc is not None and acc > self.best_acc:
                    self.best_acc = acc
                    self.save("best.pt")
                if self.ts["plots"]:
                    t1 = time.monotonic()
                    self._write_progress_images()
                    spent = time.monotonic() - t1  # budgeted as part of the validation
                    self._val_seconds += spent
                    self._val_time_run += spent

    @torch.no_grad()
    def _write_progress_images(self) -> None:
        """Rank 0, after a validation: ``results.png`` (the metrics.csv curves) and
        ``val_snapshot.png`` (a few validation images, their belief maps and decoded cuboids;
        also to TensorBoard when it is installed)."""
        from dope_hope.io.images import write_rgb
        from dope_hope.preprocess import denormalize_rgb
        from dope_hope.training.plots import SNAPSHOT_IMAGES, SnapshotItem, plot_results, snapshot_panel

        plot_results(self.metrics.csv_path, self.out / "results.png")
        n = min(SNAPSHOT_IMAGES, len(self.val_set))
        if n == 0:
            return
        self.model.eval()
        items = [self.val_set[(0, i)] for i in range(n)]  # the same frames after every validation
        images = self._to_device(torch.stack([it["image"] for it in items]), image=True)
        belief, affinity = (o.float().cpu().numpy() for o in self.model(images)[-1])
        panel = snapshot_panel(
            [SnapshotItem(denormalize_rgb(it["image"].numpy()), belief[i], affinity[i], it["keypoints"].numpy(),
                          f"step {self.step}  {self.val_set.records[i].image_path.name}")
             for i, it in enumerate(items)],
            int(self.model.stride), float(self.ts["val_peak_threshold"]))
        write_rgb(self.out / "val_snapshot.png", panel)
        self.metrics.image("val/snapshot", panel, self.step)

    def _primary_acc(self) -> float | None:
        a = self.last_val.get("val_kp_acc_decoded")
        if a is None or not math.isfinite(a):
            a = self.last_val.get("val_kp_acc")
        return a if a is not None and math.isfinite(a) else None

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
        from dope_hope.io.atomic import remove_stale_temporaries
        from dope_hope.io.paths import output_dir

        self._t0 = time.monotonic()
        self._steps_this_run = 0
        self._val_seconds = 0.0
        self._val_time_run = 0.0
        self._plan_t1: float | None = None
        self._plan_val1 = 0.0
        self._plan_n1 = 1
        output_dir(self.out)
        if self.dist.main:  # a process killed while writing leaves .last.<random>.tmp.pt
            remove_stale_temporaries(self.out, {"last", "best", "summary", "metrics"})
        resumed = self.job.resume is not None
        self.metrics = MetricsLog(self.out, self.dist.main, keep_rows=self._metrics_rows if resumed else 0,
                                  purge_step=self.step + 1 if resumed else None)
        handlers = {}
        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, self._on_signal)
        except ValueError:  # not the main thread: no signal handling
            handlers = {}
        try:
            self._loop()
        finally:
            for sig, h in handlers.items():
                signal.signal(sig, h)
            self.metrics.close()
        status = self.stop_reason or "completed"
        if status == "completed" and self.planned_steps is not None and self.planned_steps < self._nominal_total:
            status = "time_limit"  # ended at the step the budget allowed
        summary = {
            "status": status, "step": self.step, "epoch": self.epoch, "total_steps": self.total_steps,
            "planned_steps": self.planned_steps, "budget_used_s": round(self.budget_used(), 2),
            "elapsed_s": round(self.elapsed(), 2), "train_frames": len(self.train_set), "val_frames": len(self.val_set),
            "best_val_kp_acc": self.best_acc if self.best_acc >= 0 else None, **self.last_val,
            "object": self.object, "objects": [o.name for o in self.objects],
            "last": str(self.out / "last.pt"), "rank": self.dist.rank,
        }
        if self.dist.main:
            from dope_hope.io.atomic import atomic_write_text
            atomic_write_text(self.out / "summary.json", json.dumps(summary, indent=2, default=str))
        if self.dist.active:
            dist.barrier()
        return summary

    def _loop(self) -> None:
        from tqdm import tqdm

        ts = self.ts
        log_every = max(1, int(ts["log_every"]))
        ck_steps = int(ts["checkpoint_every_steps"] or 0)
        ck_epochs = int(ts["checkpoint_every"] or 0)
        bar = tqdm(total=self.total_steps, initial=self.step, disable=not (self.job.progress and self.dist.main),
                   unit="step", dynamic_ncols=True, desc="train")
        run_loss, run_n, t_log = 0.0, 0, time.monotonic()

        def log_train() -> None:
            """One train row: the mean loss of the steps since the last row (every log_every
            steps, before each validation and at the end, so that short runs have rows)."""
            nonlocal run_loss, run_n, t_log
            if run_n == 0:
                return
            if self.dist.main:
                dt = time.monotonic() - t_log
                ips = run_n * self.batch_size * self.dist.world_size / max(dt, 1e-9)
                lr = self.optimizer.param_groups[0]["lr"]
                self.metrics.write("train", step=self.step, epoch=self.epoch, lr=lr,
                                   loss=run_loss / run_n, images_per_s=round(ips, 2),
                                   time_s=round(self._time_used_before + self.elapsed(), 2))
                bar.set_postfix(loss=f"{run_loss / run_n:.4f}", lr=f"{lr:.2e}", img_s=f"{ips:.1f}")
            run_loss, run_n, t_log = 0.0, 0, time.monotonic()

        try:
            while self.epoch < self.epochs and self.step < self.total_steps and self.stop_reason is None:
                if self.batch_in_epoch < self.steps_per_epoch:
                    self.sampler.set_epoch(self.epoch, skip=self.batch_in_epoch * self.batch_size)
                    loader = self._loader(self.train_set, self.sampler, self.batch_size, drop_last=True)
                    it = iter(loader)
                    while self.batch_in_epoch < self.steps_per_epoch and self.step < self.total_steps:
                        try:
                            batch = next(it)
                        except StopIteration:
                            break
                        except RuntimeError:
                            if self.stop_reason is not None:  # a worker died of the same Ctrl-C
                                break
                            raise
                        self._report_bad(batch["bad_files"])
                        loss = self.train_step(batch)
                        self.step += 1
                        self.batch_in_epoch += 1
                        self._steps_this_run += 1
                        run_loss += loss
                        run_n += 1
                        bar.update(1)
                        self._maybe_plan()
                        if self.step % log_every == 0:
                            log_train()
                        if self.job.on_step is not None:
                            self.job.on_step(self, self.step)
                        if ck_steps and self.step % ck_steps == 0:
                            self.save("last.pt")
                        if self._agree_stop():
                            break
                    del it, loader
                if self.stop_reason in ("interrupted", "terminated"):
                    break
                # the epoch's batches are done (or the step / time budget ran out inside it)
                if self.val_done_epoch != self.epoch:
                    log_train()  # the curves in results.png reach the validated step
                    self._end_of_epoch()
                    t_log = time.monotonic()  # images/s counts training time only
                self._maybe_plan(epoch_end=True)
                if self.step >= self.total_steps or self.stop_reason is not None:
                    break
                self.epoch += 1
                self.batch_in_epoch = 0
                if ck_epochs and self.epoch % ck_epochs == 0:
                    self.save("last.pt")
                self._agree_stop()
            if self.stop_reason not in ("interrupted", "terminated"):
                log_train()  # (a stopped run leaves its partial window out: resumed, it logs as uninterrupted)
        finally:
            bar.close()
        self.save("last.pt")


def load_init_weights(model: nn.Module, path: str | Path) -> None:
    """Copy a dope-hope checkpoint's network weights into ``model`` (``--init``); a one-object
    start of a model of N > 1 objects is widened first (every group a copy of its one group:
    :func:`dope_hope.model.network.widen_to_objects`).

    Raises ModelFileError naming the file when it is no checkpoint or was trained with
    another architecture than ``model`` (compare the configs' ``model`` sections).
    """
    from dope_hope.model.checkpoint import check_state_dict, load_checkpoint
    from dope_hope.model.network import num_objects_of, widen_to_objects

    ck = load_checkpoint(path)
    state = ck["model"]
    n = int(getattr(model, "num_objects", 1))
    widen = n > 1 and num_objects_of(ck["config"]) == 1
    if widen:
        state = widen_to_objects(state, ck["config"], n)
    check_state_dict(model.state_dict(), state, path)
    model.load_state_dict(state, strict=True)
    log.info("initialised the network from %s%s", path, f" (its one object widened to {n})" if widen else "")


def per_object_accuracy(names: list[str], hits: torch.Tensor) -> dict[str, float]:
    """``val_kp_acc/<name>`` and ``val_kp_acc_decoded/<name>`` of each object of a run of
    several (``hits``: (N, 4) found, visible, found_decoded, visible_decoded); {} for one."""
    if len(names) < 2:
        return {}
    out = {}
    for name, (f, v, fd, vd) in zip(names, hits.tolist()):
        out[f"val_kp_acc/{name}"] = f / v if v else float("nan")
        out[f"val_kp_acc_decoded/{name}"] = fd / vd if vd else float("nan")
    return out


def _extra(ck: dict[str, Any]) -> dict[str, Any]:
    extra = ck.get("extra")
    return extra if isinstance(extra, dict) else {}


def train(job: TrainJob, config: dict[str, Any]) -> dict[str, Any]:
    """Run a training job; returns the summary (status completed | time_limit | interrupted |
    terminated, step, epoch, validation numbers, object, path of last.pt)."""
    trainer = None
    try:
        trainer = Trainer(job, config)
        return trainer.run()
    finally:
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
