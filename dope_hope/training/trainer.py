"""The training loop: data, loss, optimizer + schedule, validation, steps and epochs, DDP.

:class:`Trainer` holds the loop's state (step, epoch, :class:`~dope_hope.training.resume.RunProgress`)
and composes its parts, each an object with its own state and explicit inputs: the time
budget (:class:`~dope_hope.training.time_budget.TimeBudget`, fed the start, the steps and the
validations' seconds, answering with the step the run ends at), the checkpoints
(:class:`~dope_hope.training.resume.CheckpointStore`, handed the state to write), the stop
requests (:class:`~dope_hope.training.stopping.StopControl`), the thresholds' choice at the end
(:class:`~dope_hope.training.calibration.RunThresholds`) and the train rows
(:class:`~dope_hope.training.train_rows.TrainRows`).

:func:`train` runs one job described by :class:`~dope_hope.training.settings.TrainJob` and a
recipe (:class:`~dope_hope.training.settings.TrainConfig`: sections ``model``, ``input``,
``targets``, ``train``, ``augment``; see ``dope_hope/configs/lite.yaml``), checked once and
read as attributes.

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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from dope_hope.devices import native_bf16
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import KEYPOINT_ORDER
from dope_hope.io.atomic import atomic_write_text, remove_stale_temporaries
from dope_hope.io.images import write_rgb
from dope_hope.io.paths import output_dir
from dope_hope.model.checkpoint import TrainingState, restore_rng_state
from dope_hope.model.network import build_model, load_backbone_weights
from dope_hope.preprocess import denormalize_rgb
from dope_hope.training.augment import AugmentParams
from dope_hope.training.calibration import RunThresholds
from dope_hope.training.dataset import DopeDataset, EpochSampler, collate, report_bad_file, split_records
from dope_hope.training.distributed import init_distributed
from dope_hope.training.init_weights import load_init_weights
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
from dope_hope.training.resume import CheckpointStore, RunProgress, checkpoint_extra, job_record, resumed_job
from dope_hope.training.schedule import LrLambda
from dope_hope.training.settings import TrainConfig, TrainJob, TrainSettings, run_recipe
from dope_hope.training.sources import check_instances, scan_training_data
from dope_hope.training.stopping import StopControl
from dope_hope.training.time_budget import (
    LOADER_PREFETCH,
    BudgetShape,
    TimeBudget,
    after_run_validations,
    collect_in_validation,
    collections_at_validations,
)
from dope_hope.training.train_rows import TrainRows
from dope_hope.training.validation import object_hits, per_object_accuracy

log = logging.getLogger(__name__)


# =============================================================================== trainer
class Trainer:
    """One training job; :meth:`run` returns a summary dict (see :func:`train`).

    Args:
        job: what to train on and where to write (its ``overrides`` go over the recipe).
        config: the recipe (settings, or a recipe mapping over the defaults); a resumed run
            trains with its checkpoint's recipe instead.
    """

    def __init__(self, job: TrainJob, config: TrainConfig | Mapping[str, Any] | None = None):
        self.job = job
        clock = job.clock or time.monotonic
        started = clock() if job.started is None else job.started  # the budget counts from here
        self.dist, self.device = init_distributed(job.device)
        self.cuda = self.device.type == "cuda"
        if not self.dist.main:  # rank 0 alone reports (skipped files, progress, results)
            logging.getLogger("dope_hope").setLevel(logging.ERROR)
        self.out = Path(job.out)
        self.stop = StopControl(self.dist.active, self.device if self.cuda else "cpu")

        ck, recorded = resumed_job(job)
        recipe = run_recipe(config, job.overrides, recorded)
        check_class_names(job.class_names)
        self.recipe = with_num_objects(recipe, len(job.class_names))
        ts = self.recipe.train
        if ts.threads:
            torch.set_num_threads(int(ts.threads))
        self.seed = int(ts.seed)
        if ck is None:
            random.seed(self.seed)
            np.random.seed(self.seed % (2**32))
            torch.manual_seed(self.seed)

        self.model = build_model(self.recipe.to_dict())  # before the data: stride comes from the model
        if job.backbone_weights is not None:
            load_backbone_weights(self.model, job.backbone_weights)
        self._build_data(job, ck is None)
        self.thresholds = RunThresholds(ts.calibrate_thresholds, ts.val_every, job, self.out, str(self.device))
        self.checkpoints = CheckpointStore(self.out)
        self._build_optimizer(ts)
        self.budget = TimeBudget(self._budget_shape(ts), clock, started)
        self.step = 0
        self.epoch = 0
        self.progress = RunProgress()
        self.metrics: MetricsLog | None = None
        if ck is not None:
            self._restore(ck, TrainSettings.from_mapping(recorded.get("train")) if recorded else ts)
        self.ddp_model: nn.Module = self.model
        if self.dist.active:
            self.ddp_model = nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.cuda else None)

    def _build_data(self, job: TrainJob, new_run: bool) -> None:
        """The training and validation sets, samplers and the run's objects (and, for a new
        run, the starting weights once the data checks passed)."""
        recipe, ts = self.recipe, self.recipe.train
        stride = int(self.model.stride)
        scan = dict(min_visibility=float(ts.min_visibility), include_empty=bool(ts.include_empty_frames),
                    progress=job.progress and self.dist.main)
        records, _ = scan_training_data(job.data, job.class_names, KEYPOINT_ORDER, **scan)
        check_instances(records, job.class_names, job.data)
        if job.val:
            val_records, _ = scan_training_data(job.val, job.class_names, KEYPOINT_ORDER, **scan)
            if not val_records:
                raise InputFileError(", ".join(str(p) for p in job.val), "no readable validation frames")
        else:
            records, val_records = split_records(records, float(ts.val_fraction), self.seed)
        if new_run:  # after the data checks: a bad folder or class is the only line printed
            if job.init_weights is not None:
                load_init_weights(self.model, job.init_weights)
            if job.init_reason:
                log.info("start: %s", job.init_reason)
        self._set_objects(records)
        (records, val_records), self.symmetry_permutations, lines = relabel_objects(
            recipe.targets.symmetry, job, self.objects, [records, val_records])
        for line in lines:
            log.info("symmetry-aware labels: %s", line)
        common = dict(input_hw=recipe.input.size, stride=stride, sigma=float(recipe.targets.sigma),
                      radius=float(recipe.targets.radius), seed=self.seed, max_instances=int(ts.max_instances),
                      num_objects=len(self.objects))
        cache_mb = float(ts.frame_cache_mb)  # one budget: the training frames first
        self.train_set = DopeDataset(records, augment=recipe.augment, frame_cache_mb=cache_mb, **common)
        if self.train_set.frame_cache is not None:
            cache_mb -= self.train_set.frame_cache.reserved_mb
        self.val_set = DopeDataset(val_records, augment=AugmentParams(enabled=False),
                                   frame_cache_mb=cache_mb, **common)
        self.batch_size = int(ts.batch_size)
        if len(self.train_set) < self.batch_size * self.dist.world_size:
            raise ConfigError(f"{len(self.train_set)} training frames are fewer than one batch "
                              f"({self.batch_size} x {self.dist.world_size} processes); lower --batch-size")
        self.sampler = EpochSampler(len(self.train_set), self.seed, True, self.dist.rank, self.dist.world_size)
        self.val_sampler = EpochSampler(len(self.val_set), self.seed, False, self.dist.rank, self.dist.world_size)
        self.steps_per_epoch = len(self.sampler) // self.batch_size

    def _build_optimizer(self, ts: TrainSettings) -> None:
        """Device placement, precision, optimizer, run length and LR schedule."""
        self.model.to(self.device)
        self.channels_last = bool(ts.channels_last)
        self.amp = bool(ts.amp) and native_bf16(self.device.type)
        if self.dist.main and bool(ts.amp) != self.amp:
            log.info("train.amp: float32 (this %s has no native bfloat16)", self.device.type.upper())
        if self.channels_last:
            self.model.to(memory_format=torch.channels_last)
        opt_cls = torch.optim.AdamW if ts.optimizer == "adamw" else torch.optim.Adam
        self.optimizer = opt_cls(self.model.parameters(), lr=float(ts.lr),
                                 weight_decay=float(ts.weight_decay), betas=tuple(ts.betas),
                                 fused=self.device.type in ("cpu", "cuda"))  # one kernel: 3.4x the step on 2 cores
        self.epochs = int(ts.epochs)
        self.total_steps = int(ts.steps) if ts.steps else self.epochs * self.steps_per_epoch
        if ts.steps:
            self.epochs = math.ceil(self.total_steps / self.steps_per_epoch)
        self.nominal_steps = self.total_steps
        # Under a time limit the schedule follows the budget's plans, unless steps were given.
        self.lr_lambda = LrLambda(ts.schedule, self.total_steps, int(ts.warmup_steps), float(ts.min_lr_factor),
                                  int(ts.step_epochs) * self.steps_per_epoch, float(ts.step_gamma),
                                  ts.cosine_replan, float(ts.decay_share))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, self.lr_lambda)

    def _budget_shape(self, ts: TrainSettings) -> BudgetShape:
        """What the time budget is told of this run once (:class:`BudgetShape`)."""
        h, w = self.recipe.input.size
        crop = self.train_set.augment.crop or (h, w)
        return BudgetShape(
            limit_s=float(ts.time_limit_min) * 60.0 if ts.time_limit_min else None,
            sets_horizon=bool(ts.time_limit_min) and not ts.steps, nominal_steps=self.nominal_steps,
            steps_per_epoch=self.steps_per_epoch, val_every=int(ts.val_every),
            val_batches=math.ceil(len(self.val_set) / max(1, int(ts.val_batch_size or self.batch_size))),
            val_area_ratio=max(1.0, h * w / (crop[0] * crop[1])),
            first_window_steps=1 + int(ts.workers) * LOADER_PREFETCH,
            horizon_estimate_after=int(ts.horizon_estimate_after),
            after_run_validations=after_run_validations(self.thresholds.calibrates(len(self.val_set)),
                                                        len(self.objects)))

    def _set_objects(self, records: list[Any]) -> None:
        """The run's objects (:mod:`dope_hope.training.objects`): ``objects``, the checkpoint's
        ``object`` (one entry, or the list of several) and where the sizes came from."""
        self.objects = run_objects(self.job, records)
        for obj in self.objects:
            log.info("symmetries: %s: %s", obj.name, obj.symmetry_source)
        self.object = checkpoint_objects(self.objects)
        self.size_source = self.objects[0].size_source if len(self.objects) == 1 else \
            {o.name: o.size_source for o in self.objects}

    # ------------------------------------------------------------------ checkpoints and resume
    def save(self, name: str) -> Path:
        """Write ``out/name`` atomically (rank 0 only): the weights, optimizer, schedule,
        counters, the budget's time and plans and the job; returns its path."""
        if not self.dist.main:
            return self.out / name
        extra = {**self.progress.extra(self.metrics.rows if self.metrics is not None else self.progress.metrics_rows),
                 **self.budget.state(), "size_source": self.size_source, "world_size": self.dist.world_size,
                 "job": job_record(self.job, len(self.objects) > 1)}
        return self.checkpoints.save(name, self.model, self.recipe, self.object,
                                     TrainingState(self.optimizer, self.scheduler, self.step, self.epoch, extra))

    def _restore(self, ck: dict[str, Any], saved: TrainSettings) -> None:
        """Continue from checkpoint ``ck``; ``saved``: its ``train`` settings (a length or
        budget given now that differs wins, said in one line)."""
        self.model.load_state_dict(ck["model"])
        if ck.get("optimizer") is not None:
            self.optimizer.load_state_dict(ck["optimizer"])
        if ck.get("scheduler") is not None:
            self.scheduler.load_state_dict(ck["scheduler"])
        self.step = int(ck.get("step", 0))
        self.epoch = int(ck.get("epoch", 0))
        extra = checkpoint_extra(ck)
        self.progress = RunProgress.from_extra(extra, self.epoch, self.steps_per_epoch)
        self.budget.restore(extra)
        if ck.get("rng"):
            restore_rng_state(ck["rng"])
        if self.dist.main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", self.job.resume, self.step, self.epoch,
                     self.progress.batch_in_epoch)
        self._resume_length(extra, saved)

    def _resume_length(self, extra: dict[str, Any], saved: TrainSettings) -> None:
        """The resumed run's end: the checkpoint's plans when its length and budget are kept;
        a length (``steps``, ``epochs``) or budget given now that differs wins, at once (one
        line says so) and the learning rate falls from where it is to the new end."""
        ts, plan = self.recipe.train, self.budget.plan
        plans = extra.get("plans")  # a run that reached its end (its rate at the floor) restarts warm when longer
        finished = ts.schedule in LrLambda.REPLANNED and (
            self.lr_lambda.ended(self.step) or bool(plans) and self.step >= int(plans[-1]["end"]))
        if plans is None and extra.get("planned_steps") is not None and plan is not None:
            self.total_steps = min(self.nominal_steps, int(extra["planned_steps"]))  # one fixed plan: measured again
        changed = [k for k in ("steps", "epochs", "time_limit_min") if getattr(ts, k) != getattr(saved, k)]
        if plan is not None and plans and "time_limit_min" not in changed:
            plan.plans = [dict(p) for p in plans]
            self.total_steps = min(self.nominal_steps, int(plans[-1]["budget_end"]))
        if plan is not None and plans and changed:  # planned again at once, at the last plan's speed
            plan.plans = [dict(p) for p in plans]
            end = self.budget.plan_now(self.step, "length or budget changed at resume") if self.dist.main else None
            self._end_at(self._broadcast_end(end))
        elif changed and plan is None:
            self.total_steps = self.nominal_steps
        if changed and ts.schedule in LrLambda.REPLANNED and not self.budget.shape.sets_horizon:
            self.lr_lambda.replan(self.step, max(self.step + 1, self.total_steps))
        if restart := changed and finished and self.total_steps > self.step:
            self.lr_lambda.restart(self.step, self.total_steps)
        if changed and self.dist.main:
            now = ", ".join(f"train.{k} {getattr(ts, k)}" for k in changed)
            before = ", ".join(f"{getattr(saved, k)}" for k in changed)
            tail = (f", or earlier when the {ts.time_limit_min:g}-min time budget is spent"
                    if plan is not None and self.total_steps >= self.nominal_steps else "")
            warm = f"; the run had ended: its learning rate restarts warm to {ts.lr:g} (SGDR)" if restart else ""
            log.warning("resume: %s given now win(s) over the checkpoint's %s: the run ends at step %d%s%s",
                        now, before, self.total_steps, tail, warm)

    # ------------------------------------------------------------------ the run's end
    def request_stop(self, reason: str = "interrupted") -> None:
        """Stop after the current step (what Ctrl-C / SIGTERM do)."""
        self.stop.request(reason)

    def _follow_budget(self, validated: bool = False) -> None:
        """Time-limited run, after each step (``validated``: after a validation): rank 0 asks
        the budget whether the run's end moves; every rank takes the end it decided. At the
        end, only a validation after an end set from an estimated validation cost asks again."""
        if self.budget.plan is None:
            return
        if self.step >= self.total_steps and not (validated and self.budget.end_rests_on_estimate):
            return
        end = self._broadcast_end(self.budget.decide_end(self.step, validated) if self.dist.main else None)
        if end is not None:
            self._end_at(end)

    def _broadcast_end(self, end: int | None) -> int | None:
        """Rank 0's end step (or None) on every rank."""
        if not self.dist.active:
            return end
        t = torch.tensor([-1 if end is None else end], dtype=torch.int64, device=self.device if self.cuda else "cpu")
        dist.broadcast(t, 0)
        return None if int(t.item()) < 0 else int(t.item())

    def _end_at(self, end: int) -> None:
        """End the run at step ``end``; the cosine or wsd's decay (when the budget sets it) falls to it."""
        if end != self.total_steps and self.budget.shape.sets_horizon:
            self.lr_lambda.replan(self.step, max(self.step + 1, end))
        self.total_steps = end

    # ------------------------------------------------------------------ steps
    def _loader(self, dataset: Any, sampler: Any, batch_size: int, drop_last: bool) -> torch.utils.data.DataLoader:
        workers = int(self.recipe.train.workers)
        return torch.utils.data.DataLoader(
            dataset, batch_size=batch_size, sampler=sampler, num_workers=workers, collate_fn=collate,
            drop_last=drop_last, pin_memory=self.cuda, persistent_workers=False,
            prefetch_factor=LOADER_PREFETCH if workers > 0 else None,
            multiprocessing_context="fork" if workers > 0 and os.name == "posix" else None)

    def _report_bad(self, files: list[str]) -> None:
        for f in files:
            report_bad_file(f, "unreadable image, replaced by another frame")

    def _to_device(self, x: torch.Tensor, image: bool = False) -> torch.Tensor:
        x = x.to(self.device, non_blocking=True)
        if image and self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def train_step(self, batch: dict[str, Any]) -> float:
        ts = self.recipe.train
        images = self._to_device(batch["image"], image=True)
        belief, affinity = self._to_device(batch["belief"]), self._to_device(batch["affinity"])
        loss = optimizer_step(self.ddp_model, self.optimizer, images, belief, affinity, amp=self.amp,
                              belief_weight=float(ts.belief_weight), affinity_weight=float(ts.affinity_weight),
                              grad_clip=ts.grad_clip, foreground_weight=float(ts.foreground_weight))
        self.scheduler.step()
        return loss

    @torch.no_grad()
    def validate(self) -> dict[str, Any]:
        """Loss and keypoint accuracy on the validation frames (all ranks; summed across)."""
        ts = self.recipe.train
        self.model.eval()
        stride = int(self.model.stride)
        radius = float(ts.val_radius_px)
        thr = float(ts.val_peak_threshold)
        n_obj = len(self.objects)
        # loss*n, n, then per object: found, visible, found_dec, visible_dec
        sums = torch.zeros(2 + 4 * n_obj, dtype=torch.float64)
        self.val_sampler.set_epoch(0)
        bs = int(ts.val_batch_size or self.batch_size)
        for batch in self._loader(self.val_set, self.val_sampler, bs, drop_last=False):
            self._report_bad(batch["bad_files"])
            images = self._to_device(batch["image"], image=True)
            outputs = self.model(images)  # float32, as inference runs it (train.amp is for training)
            n = images.shape[0]
            loss = stage_loss(outputs, self._to_device(batch["belief"]), self._to_device(batch["affinity"]),
                              float(ts.belief_weight), float(ts.affinity_weight), float(ts.foreground_weight))
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
            **per_object_accuracy([o.name for o in self.objects], sums[2:].reshape(n_obj, 4).tolist()),
        }

    def _end_of_epoch(self) -> bool:
        """Validate (rank 0 also logs, saves best.pt, draws the plots) when this epoch's end is
        a validation's; returns whether it validated. A time-limited run skips the validation
        of an epoch end from which its planned end is less than one validation interval away
        (the final validation replaces it; the budget plans count it so)."""
        every = int(self.recipe.train.val_every)
        last_epoch = self.epoch + 1 >= self.epochs or self.step >= self.total_steps or self.stop.reason is not None
        if self.budget.plan is not None and self.step < self.total_steps < self.step + every * self.steps_per_epoch:
            return False
        validates = every > 0 and ((self.epoch + 1) % every == 0 or last_epoch)
        if validates:
            t0 = self.budget.clock()  # the validation's cost, as the time budget plans with it: all of this block
            collect_in_validation()
            progress = self.progress
            progress.last_val = self.validate()
            progress.val_done_epoch = self.epoch
            if self.dist.main:
                self.metrics.write("val", step=self.step, epoch=self.epoch, time_s=round(self.budget.used(), 2),
                                   **{k: v for k, v in progress.last_val.items()
                                      if k in ("val_loss", "val_kp_acc", "val_kp_acc_decoded") or "/" in k})
                log.info("epoch %d step %d: val loss %.5f, keypoints within %g px %.3f (peaks) %.3f (decoded)",
                         self.epoch, self.step, progress.last_val["val_loss"], progress.last_val["val_radius_px"],
                         progress.last_val["val_kp_acc"], progress.last_val["val_kp_acc_decoded"])
                acc = self._primary_acc()
                if acc is not None and acc > progress.best_acc:
                    progress.best_acc = acc
                    self.save("best.pt")
                if self.recipe.train.plots:
                    self._write_progress_images()
            self.budget.validated(self.budget.clock() - t0)
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
            int(self.model.stride), float(self.recipe.train.val_peak_threshold))
        write_rgb(self.out / "val_snapshot.png", panel)
        self.metrics.image("val/snapshot", panel, self.step)

    def _primary_acc(self) -> float | None:
        a = self.progress.last_val.get("val_kp_acc_decoded")
        if a is None or not math.isfinite(a):
            a = self.progress.last_val.get("val_kp_acc")
        return a if a is not None and math.isfinite(a) else None

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
        output_dir(self.out)
        if self.dist.main:  # a process killed while writing leaves .last.<random>.tmp.pt
            remove_stale_temporaries(self.out, {"last", "best", "summary", "metrics"})
        resumed = self.job.resume is not None
        self.metrics = MetricsLog(self.out, self.dist.main, keep_rows=self.progress.metrics_rows if resumed else 0,
                                  purge_step=self.step + 1 if resumed else None)
        try:
            with self.stop.signals(), collections_at_validations():
                self._loop()
        finally:
            self.metrics.close()
        status = self.stop.reason or "completed"
        planned = self.budget.planned_steps
        if status == "completed" and planned is not None and planned < self.nominal_steps:
            status = "time_limit"  # ended at the step the budget allowed
        thresholds = {}
        if self.stop.reason is None and self.dist.main:
            thresholds = self.thresholds.choose(self.progress.best_acc >= 0, self.val_set.records, self.objects)
        best = self.progress.best_acc
        summary = {
            "status": status, "step": self.step, "epoch": self.epoch, "total_steps": self.total_steps,
            "planned_steps": planned, "budget_used_s": round(self.budget.used(), 2),
            "elapsed_s": round(self.budget.elapsed(), 2), "train_frames": len(self.train_set),
            "val_frames": len(self.val_set), "best_val_kp_acc": best if best >= 0 else None, **self.progress.last_val,
            "object": self.object, "objects": [o.name for o in self.objects],
            "last": str(self.out / "last.pt"), "rank": self.dist.rank, **thresholds,
        }
        if self.dist.main:
            atomic_write_text(self.out / "summary.json", json.dumps(summary, indent=2, default=str))
        if self.dist.active:
            dist.barrier()
        return summary

    def _log_row(self, rows: TrainRows) -> None:
        """A train row of the loss since the last one (none when no step was made since); the
        partial sum of a stopped run is in its checkpoint, so a resumed run logs the row an
        uninterrupted one does."""
        loss_sum, n = self.progress.loss_window
        if n == 0:
            return
        rows.row(self.step, self.epoch, self.optimizer.param_groups[0]["lr"], loss_sum / n,
                 round(self.budget.used(), 2))
        self.progress.loss_window = [0.0, 0]

    def _loop(self) -> None:
        """Epochs of steps until the step count, the epochs or the time budget end, or a stop;
        validation at epoch ends; ``last.pt`` at the end."""
        ck_epochs = int(self.recipe.train.checkpoint_every or 0)
        rows = TrainRows(self.metrics, self.total_steps, self.step, self.job.progress and self.dist.main,
                         self.batch_size * self.dist.world_size, self.dist.main)
        self.budget.begin_steps()  # (the time budget's step speed leaves the start-up out)
        try:
            while self.epoch < self.epochs and self.step < self.total_steps and self.stop.reason is None:
                if self.progress.batch_in_epoch < self.steps_per_epoch:
                    self._epoch_steps(rows)
                if self.stop.reason in ("interrupted", "terminated"):
                    break
                # the epoch's batches are done (or the step / time budget ran out inside it)
                ended = self.step >= self.total_steps
                if self.progress.val_done_epoch != self.epoch:
                    self._log_row(rows)  # the curves in results.png reach the validated step
                    if self._end_of_epoch():
                        rows.restart_clock()  # images/s counts training time only
                        self._follow_budget(validated=True)
                if self.step >= self.total_steps or self.stop.reason is not None:
                    break
                if ended and self.progress.batch_in_epoch < self.steps_per_epoch:
                    continue  # the end moved past a validation made inside the epoch: the epoch goes on
                self.epoch += 1
                self.progress.batch_in_epoch = 0
                if ck_epochs and self.epoch % ck_epochs == 0:
                    self.save("last.pt")
                self.stop.agree()
            if self.stop.reason not in ("interrupted", "terminated"):
                self._log_row(rows)  # (a stopped run keeps its partial window in last.pt)
        finally:
            rows.close()
        self.save("last.pt")

    def _epoch_steps(self, rows: TrainRows) -> None:
        """The remaining steps of this epoch (resumed mid-epoch: from its next batch), until
        the step count or the time budget ends or a stop is agreed."""
        log_every = max(1, int(self.recipe.train.log_every))
        ck_steps = int(self.recipe.train.checkpoint_every_steps or 0)
        progress = self.progress
        self.sampler.set_epoch(self.epoch, skip=progress.batch_in_epoch * self.batch_size)
        loader = self._loader(self.train_set, self.sampler, self.batch_size, drop_last=True)
        it = iter(loader)
        while progress.batch_in_epoch < self.steps_per_epoch and self.step < self.total_steps:
            try:
                batch = next(it)
            except StopIteration:
                break
            except RuntimeError:
                if self.stop.reason is not None:  # a worker died of the same Ctrl-C
                    break
                raise
            self._report_bad(batch["bad_files"])
            loss = self.train_step(batch)
            self.step += 1
            progress.batch_in_epoch += 1
            self.budget.stepped()
            progress.loss_window = [progress.loss_window[0] + loss, progress.loss_window[1] + 1]
            rows.stepped()
            if self.job.on_step is not None:
                self.job.on_step(self, self.step)
            self._follow_budget()
            rows.follow_total(self.total_steps)
            if self.step % log_every == 0:
                self._log_row(rows)
            if ck_steps and self.step % ck_steps == 0:
                self.save("last.pt")
            if self.stop.agree():
                break


def train(job: TrainJob, config: TrainConfig | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Run a training job with the recipe ``config`` (:class:`Trainer`); returns the summary
    (status completed | time_limit | interrupted | terminated, step, epoch, validation numbers,
    object, path of last.pt)."""
    trainer = None
    try:
        trainer = Trainer(job, config)
        return trainer.run()
    finally:
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
