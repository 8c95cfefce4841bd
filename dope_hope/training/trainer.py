"""The training loop: data, loss, optimizer + schedule, validation, steps and epochs, DDP.

Parts of :class:`Trainer` with a module each: the time budget
(:mod:`~dope_hope.training.time_budget`), checkpoints and resume
(:mod:`~dope_hope.training.resume`), Ctrl-C / SIGTERM (:mod:`~dope_hope.training.stopping`),
the thresholds' choice at the end (:mod:`~dope_hope.training.calibration`).

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
* Time limit: the budget belongs to the run (the time of every process so far, from the
  trainer's start). After the batches the loader fetched ahead and ``horizon_estimate_after``
  more steps (or the first epoch, if shorter) the measured speed turns the budget left into
  the step the run ends at; the run plans again from the speed of its recent steps at every
  validation and whenever a share of the budget has passed (:mod:`~dope_hope.training.budget`),
  and stops early when one more step and the final validation (and the thresholds' choice
  below) would not fit. The cosine
  follows the plans (unless steps were given). The plans and the time used are saved in every
  checkpoint: a resumed run continues with them and plans again from its own measurements
  (with the same measurements, e.g. an injected clock, it ends with the same weights).
* The end of a run that was not stopped: each object's score threshold chosen on the
  validation frames and recorded in best.pt (:mod:`~dope_hope.training.calibration`).
* Ctrl-C / SIGTERM: finish the current step, write ``last.pt`` (with the partial loss average
  of the current log row), return ``interrupted`` / ``terminated``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import random
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from dope_hope.config import merge
from dope_hope.devices import native_bf16
from dope_hope.errors import ConfigError, InputFileError, ModelFileError
from dope_hope.geometry import KEYPOINT_ORDER
from dope_hope.io.atomic import atomic_write_text, remove_stale_temporaries
from dope_hope.io.images import write_rgb
from dope_hope.io.paths import output_dir
from dope_hope.model.checkpoint import check_state_dict, load_checkpoint
from dope_hope.model.lite import deepen_stages, stage_channels_of, stage_count_of, widen_stage_channels
from dope_hope.model.network import build_model, load_backbone_weights, num_objects_of, widen_to_objects
from dope_hope.preprocess import denormalize_rgb
from dope_hope.training.augment import AugmentParams
from dope_hope.training.budget import BudgetPlan
from dope_hope.training.calibration import RunThresholds
from dope_hope.training.dataset import DopeDataset, EpochSampler, collate, report_bad_file, split_records
from dope_hope.training.distributed import init_distributed
from dope_hope.training.loss import optimizer_step, stage_loss
from dope_hope.training.metrics_log import MetricsLog
from dope_hope.training.objects import (
    check_class_names,
    checkpoint_objects,
    relabel_objects,
    run_objects,
    with_num_objects,
)
from dope_hope.training.plots import SNAPSHOT_IMAGES, SnapshotItem, plot_results, snapshot_panel
from dope_hope.training.resume import RunCheckpoints, resumed_job
from dope_hope.training.schedule import LrLambda
from dope_hope.training.settings import (
    TrainJob,
    check_config_keys,
    input_hw,
    targets_settings,
    train_settings,
)
from dope_hope.training.sources import check_instances, scan_training_data
from dope_hope.training.stopping import StopControl
from dope_hope.training.time_budget import (
    LOADER_PREFETCH,
    TimeBudgetControl,
    collect_in_validation,
    collections_at_validations,
)
from dope_hope.training.validation import object_hits

log = logging.getLogger(__name__)


# =============================================================================== trainer
class Trainer(TimeBudgetControl, RunCheckpoints, StopControl, RunThresholds):
    """One training job; :meth:`run` returns a summary dict (see :func:`train`)."""

    def __init__(self, job: TrainJob, config: dict[str, Any]):
        self.job = job
        self.clock: Callable[[], float] = job.clock or time.monotonic
        self._t0 = self.clock() if job.started is None else job.started  # the budget counts from here
        self.dist, self.device = init_distributed(job.device)
        if not self.dist.main:  # rank 0 alone reports (skipped files, progress, results)
            logging.getLogger("dope_hope").setLevel(logging.ERROR)
        self.out = Path(job.out)
        self.stop_reason: str | None = None
        self._signal_count = 0

        ck, config, saved_config = resumed_job(job, config)
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

        self.model = build_model(config)  # before the data: stride comes from the model
        if job.backbone_weights is not None:
            load_backbone_weights(self.model, job.backbone_weights)
        self._build_data(job, ck is None)
        self._build_optimizer(ts)
        self._reset_state()
        if ck is not None:
            self._restore(ck, train_settings(saved_config) if saved_config else ts)
        self.ddp_model: nn.Module = self.model
        if self.dist.active:
            self.ddp_model = nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.cuda else None)

    def _build_data(self, job: TrainJob, new_run: bool) -> None:
        """The training and validation sets, samplers and the run's objects (and, for a new
        run, the starting weights once the data checks passed)."""
        config, ts = self.config, self.ts
        hw = input_hw(config)
        tcfg = targets_settings(config)
        stride = int(self.model.stride)
        scan = dict(min_visibility=float(ts["min_visibility"]), include_empty=bool(ts["include_empty_frames"]),
                    progress=job.progress and self.dist.main)
        records, _ = scan_training_data(job.data, job.class_names, KEYPOINT_ORDER, **scan)
        check_instances(records, job.class_names, job.data)
        if job.val:
            val_records, _ = scan_training_data(job.val, job.class_names, KEYPOINT_ORDER, **scan)
            if not val_records:
                raise InputFileError(", ".join(str(p) for p in job.val), "no readable validation frames")
        else:
            records, val_records = split_records(records, float(ts["val_fraction"]), self.seed)
        if new_run:  # after the data checks: a bad folder or class is the only line printed
            if job.init_weights is not None:
                load_init_weights(self.model, job.init_weights)
            if job.init_reason:
                log.info("start: %s", job.init_reason)
        self._set_objects(records)
        (records, val_records), self.symmetry_permutations, lines = relabel_objects(
            tcfg.symmetry, job, self.objects, [records, val_records])
        for line in lines:
            log.info("symmetry-aware labels: %s", line)
        common = dict(input_hw=hw, stride=stride, sigma=float(tcfg.sigma),
                      radius=float(tcfg.radius), seed=self.seed, max_instances=int(ts["max_instances"]),
                      num_objects=len(self.objects))
        cache_mb = float(ts["frame_cache_mb"])  # one budget: the training frames first
        self.train_set = DopeDataset(records, augment=AugmentParams.from_config(config.get("augment")),
                                     frame_cache_mb=cache_mb, **common)
        if self.train_set.frame_cache is not None:
            cache_mb -= self.train_set.frame_cache.reserved_mb
        self.val_set = DopeDataset(val_records, augment=AugmentParams(enabled=False),
                                   frame_cache_mb=cache_mb, **common)
        self.batch_size = int(ts["batch_size"])
        if len(self.train_set) < self.batch_size * self.dist.world_size:
            raise ConfigError(f"{len(self.train_set)} training frames are fewer than one batch "
                              f"({self.batch_size} x {self.dist.world_size} processes); lower --batch-size")
        self.sampler = EpochSampler(len(self.train_set), self.seed, True, self.dist.rank, self.dist.world_size)
        self.val_sampler = EpochSampler(len(self.val_set), self.seed, False, self.dist.rank, self.dist.world_size)
        self.steps_per_epoch = len(self.sampler) // self.batch_size

    def _build_optimizer(self, ts: dict[str, Any]) -> None:
        """Device placement, precision, optimizer, run length, time budget and LR schedule."""
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
                                 weight_decay=float(ts["weight_decay"]), betas=tuple(ts["betas"]),
                                 fused=self.device.type in ("cpu", "cuda"))  # one kernel: 3.4x the step on 2 cores
        self.epochs = int(ts["epochs"])
        self.total_steps = int(ts["steps"]) if ts["steps"] else self.epochs * self.steps_per_epoch
        if ts["steps"]:
            self.epochs = math.ceil(self.total_steps / self.steps_per_epoch)
        self.time_limit_s = float(ts["time_limit_min"]) * 60.0 if ts["time_limit_min"] else None
        self._nominal_total = self.total_steps
        #: Under a time limit: the plans turning the budget into the step the run ends at
        #: (see _budget_step), kept in the checkpoint. None without a time limit.
        self.budget = BudgetPlan(self.time_limit_s) if self.time_limit_s is not None else None
        # Under a time limit the schedule follows the plans, unless steps were given.
        self.lr_lambda = LrLambda(ts["schedule"], self.total_steps, int(ts["warmup_steps"]), float(ts["min_lr_factor"]),
                                  int(ts["step_epochs"]) * self.steps_per_epoch, float(ts["step_gamma"]),
                                  ts["cosine_replan"], float(ts["decay_share"]))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, self.lr_lambda)

    def _reset_state(self) -> None:
        """Counters and bookkeeping of a run at its start (a resume then restores them)."""
        self.step = 0
        self.epoch = 0
        self.batch_in_epoch = 0
        self.best_acc = -1.0
        self.last_val: dict[str, Any] = {}
        self.val_done_epoch = -1
        self._time_used_before = 0.0
        self._metrics_rows = 0
        self._val_seconds = 0.0  # the last validation's seconds (plots included)
        self._val_steps: list[float] = []  # the validations' seconds over the seconds per step then (rank 0)
        self._val_time_run = 0.0  # all validations' seconds, this process
        self._steps_this_run = 0
        self._other_before = 0.0  # seconds of earlier processes not spent on steps (validations, start-ups)
        self._startup_s = 0.0  # this process's seconds before its first step
        self._window: tuple[float, float, int] | None = None  # first plan's window: (clock, val time, steps)
        self.loss_window = [0.0, 0]  # the loss sum and steps of the next train row
        self.metrics: MetricsLog | None = None

    def _set_objects(self, records: list[Any]) -> None:
        """The run's objects (:mod:`dope_hope.training.objects`): ``objects``, the checkpoint's
        ``object`` (one entry, or the list of several) and where the sizes came from."""
        self.objects = run_objects(self.job, records)
        for obj in self.objects:
            log.info("symmetries: %s: %s", obj.name, obj.symmetry_source)
        self.object = checkpoint_objects(self.objects)
        self.size_source = self.objects[0].size_source if len(self.objects) == 1 else \
            {o.name: o.size_source for o in self.objects}

    def _loader(self, dataset: Any, sampler: Any, batch_size: int, drop_last: bool) -> torch.utils.data.DataLoader:
        workers = int(self.ts["workers"])
        return torch.utils.data.DataLoader(
            dataset, batch_size=batch_size, sampler=sampler, num_workers=workers, collate_fn=collate,
            drop_last=drop_last, pin_memory=self.cuda, persistent_workers=False,
            prefetch_factor=LOADER_PREFETCH if workers > 0 else None,
            multiprocessing_context="fork" if workers > 0 and os.name == "posix" else None)

    def _report_bad(self, files: list[str]) -> None:
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

    def _end_of_epoch(self) -> bool:
        """Validate (rank 0 also logs, saves best.pt, draws the plots) when this epoch's end is
        a validation's; returns whether it validated. A time-limited run skips the validation
        of an epoch end from which its planned end is less than one validation interval away
        (the final validation replaces it; the budget plans count it so)."""
        every = int(self.ts["val_every"])
        last_epoch = self.epoch + 1 >= self.epochs or self.step >= self.total_steps or self.stop_reason is not None
        if self.budget is not None and self.step < self.total_steps < self.step + every * self.steps_per_epoch:
            return False
        validates = every > 0 and ((self.epoch + 1) % every == 0 or last_epoch)
        if validates:
            t0 = self.clock()  # the validation's cost, as the time budget plans with it: all of this block
            collect_in_validation()
            self.last_val = self.validate()
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
                    self._write_progress_images()
            self._val_seconds = self.clock() - t0
            self._val_time_run += self._val_seconds
        return validates

    @torch.no_grad()
    def _write_progress_images(self) -> None:
        """Rank 0, after a validation: ``results.png`` (the metrics.csv curves) and
        ``val_snapshot.png`` (a few validation images, their belief maps and decoded cuboids;
        also to TensorBoard when it is installed)."""
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
                          f"step {self.step}  {self.val_set.records[i].image_path.name}",
                          tuple(o.name for o in self.objects) if len(self.objects) > 1 else ())
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
        output_dir(self.out)
        if self.dist.main:  # a process killed while writing leaves .last.<random>.tmp.pt
            remove_stale_temporaries(self.out, {"last", "best", "summary", "metrics"})
        resumed = self.job.resume is not None
        self.metrics = MetricsLog(self.out, self.dist.main, keep_rows=self._metrics_rows if resumed else 0,
                                  purge_step=self.step + 1 if resumed else None)
        try:
            with self.stop_signals(), collections_at_validations():
                self._loop()
        finally:
            self.metrics.close()
        status = self.stop_reason or "completed"
        if status == "completed" and self.planned_steps is not None and self.planned_steps < self._nominal_total:
            status = "time_limit"  # ended at the step the budget allowed
        thresholds = self._calibrate() if self.stop_reason is None else {}
        summary = {
            "status": status, "step": self.step, "epoch": self.epoch, "total_steps": self.total_steps,
            "planned_steps": self.planned_steps, "budget_used_s": round(self.budget_used(), 2),
            "elapsed_s": round(self.elapsed(), 2), "train_frames": len(self.train_set), "val_frames": len(self.val_set),
            "best_val_kp_acc": self.best_acc if self.best_acc >= 0 else None, **self.last_val,
            "object": self.object, "objects": [o.name for o in self.objects],
            "last": str(self.out / "last.pt"), "rank": self.dist.rank, **thresholds,
        }
        if self.dist.main:
            atomic_write_text(self.out / "summary.json", json.dumps(summary, indent=2, default=str))
        if self.dist.active:
            dist.barrier()
        return summary

    def _loop(self) -> None:
        """Epochs of steps until the step count, the epochs or the time budget end, or a stop;
        validation at epoch ends; ``last.pt`` at the end."""
        ts = self.ts
        ck_epochs = int(ts["checkpoint_every"] or 0)
        log = _TrainRows(self)
        self._startup_s = self.elapsed()  # (the time budget's step speed leaves it out)
        try:
            while self.epoch < self.epochs and self.step < self.total_steps and self.stop_reason is None:
                if self.batch_in_epoch < self.steps_per_epoch:
                    self._epoch_steps(log)
                if self.stop_reason in ("interrupted", "terminated"):
                    break
                # the epoch's batches are done (or the step / time budget ran out inside it)
                if self.val_done_epoch != self.epoch:
                    log.row()  # the curves in results.png reach the validated step
                    if self._end_of_epoch():
                        log.restart_clock()  # images/s counts training time only
                        self._budget_step(validated=True)
                if self.step >= self.total_steps or self.stop_reason is not None:
                    break
                self.epoch += 1
                self.batch_in_epoch = 0
                if ck_epochs and self.epoch % ck_epochs == 0:
                    self.save("last.pt")
                self._agree_stop()
            if self.stop_reason not in ("interrupted", "terminated"):
                log.row()  # (a stopped run keeps its partial window in last.pt)
        finally:
            log.close()
        self.save("last.pt")

    def _epoch_steps(self, log: _TrainRows) -> None:
        """The remaining steps of this epoch (resumed mid-epoch: from its next batch), until
        the step count or the time budget ends or a stop is agreed."""
        log_every = max(1, int(self.ts["log_every"]))
        ck_steps = int(self.ts["checkpoint_every_steps"] or 0)
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
            self.loss_window = [self.loss_window[0] + loss, self.loss_window[1] + 1]
            log.stepped()
            if self.job.on_step is not None:
                self.job.on_step(self, self.step)
            self._budget_step()
            log.follow_total()
            if self.step % log_every == 0:
                log.row()
            if ck_steps and self.step % ck_steps == 0:
                self.save("last.pt")
            if self._agree_stop():
                break


class _TrainRows:
    """The progress bar and the train rows of metrics.csv: one row is the mean loss of the
    steps since the previous row (every log_every steps, before each validation and at the
    end, so that short runs have rows; the partial sum of a stopped run is in its checkpoint,
    so a resumed run logs the row an uninterrupted one does)."""

    def __init__(self, trainer: Trainer):
        self.trainer = trainer
        self.bar = tqdm(total=trainer.total_steps, initial=trainer.step,
                        disable=not (trainer.job.progress and trainer.dist.main),
                        unit="step", dynamic_ncols=True, desc="train")
        self.restart_clock()

    def restart_clock(self) -> None:
        """images/s counts this process's steps from here."""
        self.t0, self.steps = time.monotonic(), 0

    def stepped(self) -> None:
        self.steps += 1
        self.bar.update(1)

    def follow_total(self) -> None:
        """The bar's total follows a re-planned step count."""
        if self.bar.total != self.trainer.total_steps:
            self.bar.total = self.trainer.total_steps

    def row(self) -> None:
        t = self.trainer
        loss_sum, n = t.loss_window
        if n == 0:
            return
        if t.dist.main:
            ips = self.steps * t.batch_size * t.dist.world_size / max(time.monotonic() - self.t0, 1e-9)
            lr = t.optimizer.param_groups[0]["lr"]
            t.metrics.write("train", step=t.step, epoch=t.epoch, lr=lr, loss=loss_sum / n,
                            images_per_s=round(ips, 2), time_s=round(t._time_used_before + t.elapsed(), 2))
            self.bar.set_postfix(loss=f"{loss_sum / n:.4f}", lr=f"{lr:.2e}", img_s=f"{ips:.1f}")
        t.loss_window = [0.0, 0]
        self.restart_clock()

    def close(self) -> None:
        self.bar.close()


def load_init_weights(model: nn.Module, path: str | Path) -> None:
    """Copy a dope-hope checkpoint's network weights into ``model`` (``--init``); a one-object
    start of a model of N > 1 objects is widened first (every group a copy of its one group:
    :func:`dope_hope.model.network.widen_to_objects`), and a lite start's stages to a wider
    ``model.lite.stage_channels`` (:func:`dope_hope.model.lite.widen_stage_channels`): the
    network starts computing the start's maps either way; and to more ``model.stages``
    (:func:`dope_hope.model.lite.deepen_stages`: the start's last stage applied again).

    Raises ModelFileError naming the file when it is no checkpoint, was trained with another
    architecture than ``model`` (compare the configs' ``model`` sections) or holds weights
    that are not finite (NaN / inf: every step from them would be NaN).
    """
    ck = load_checkpoint(path)
    state = ck["model"]
    n = int(getattr(model, "num_objects", 1))
    widen = n > 1 and num_objects_of(ck["config"]) == 1
    if widen:
        state = widen_to_objects(state, ck["config"], n)
    own = model.state_dict()
    start_width, width = stage_channels_of(state), stage_channels_of(own)
    wider = start_width is not None and width is not None and width > start_width
    if wider:
        state = widen_stage_channels(state, width)
    start_depth, depth = stage_count_of(state), stage_count_of(own)
    deeper = start_depth >= 2 and depth > start_depth
    if deeper:
        state = deepen_stages(state, depth)
    check_state_dict(own, state, path)
    bad = [k for k, v in state.items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ModelFileError(path, f"{len(bad)} weight tensor(s) hold NaN or inf values (e.g. {bad[0]}); "
                                   "a run cannot start from them")
    model.load_state_dict(state, strict=True)
    how = [f"its one object widened to {n}"] if widen else []
    how += [f"its stages widened from {start_width} to {width} channels"] if wider else []
    how += [f"its {start_depth} stages deepened to {depth}, each new one a copy of the last"] if deeper else []
    log.info("initialised the network from %s%s", path, f" ({'; '.join(how)})" if how else "")


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
