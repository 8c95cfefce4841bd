"""The time budget of a training run, as the trainer follows it: its clock (the budget belongs
to the run: the time of every process so far), the speed measured from the steps, the plans
of :mod:`~dope_hope.training.budget` turning the budget left into the step the run ends at,
re-planned at every validation and whenever a share of the budget has passed, and the stop
when one more step and the final validation would not fit. The garbage collector's full passes
are held to the validations (:func:`collections_at_validations`), so that a validation's cost,
which the plans count, does not jump at random.

:class:`TimeBudgetControl` is a part of :class:`~dope_hope.training.trainer.Trainer`: it reads
the trainer's counters (``step``, ``steps_per_epoch``, ``ts``, ``dist``, ``clock``, the
validation times) and sets its end (``total_steps``, the cosine of ``lr_lambda``).
"""
from __future__ import annotations

import contextlib
import gc
import logging
import math
from typing import Any, Iterator

import numpy as np
import torch
import torch.distributed as dist

from dope_hope.training.budget import MIN_WINDOW_STEPS, make_plan
from dope_hope.training.settings import input_hw

#: The trainer's logger: these lines are the trainer's, under its name.
log = logging.getLogger("dope_hope.training.trainer")

#: What choosing the thresholds at a run's end costs, in validations of the same frames: a
#: fixed part (the predictor, the meshes) and a part per object of the run (its pose searches
#: at every score): measured 1.3-2.0 on six one-object runs' 100 validation frames, 3.5 on a
#: six-object run's 100 and 2.6 on its 300 (22.5 s against 8.7 s; bench/multi_object.py, AMD
#: EPYC), so 1.5 + 0.4 per object, which covers them. A model that finds little costs less
#: (nothing to search): its run ends that much under its budget.
CALIBRATION_IN_VALIDATIONS = (1.5, 0.4)

#: Batches each DataLoader worker fetches ahead (PyTorch's default, passed explicitly because the
#: time-budget plan starts its clock once those are used up).
LOADER_PREFETCH = 2


@contextlib.contextmanager
def collections_at_validations() -> Iterator[None]:
    """Inside: the objects alive at the start (the model, the frame records, the imported
    modules: they live as long as the run) are frozen out of Python's garbage collector
    (``gc.freeze``), so a full collection scans only what the run made since; the trainer
    runs one at the start of each validation (:func:`collect_in_validation`), inside the
    validation's timed cost. Without this a full collection lands at random and costs
    more the larger the heap: on the test suite's tiny runs it doubled one validation in
    three (0.19 -> 0.45 s), and a time budget that plans its final validation from the last
    ones' median overran. Unfrozen afterwards (a later run in the same process collects
    this one's objects). Where the calling program froze objects of its own, the freeze is
    left to it (Python can only unfreeze all): the collections at the validations remain."""
    if gc.get_freeze_count():
        yield
        return
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def collect_in_validation() -> None:
    """A full garbage collection at a validation's start, counted in its cost (see
    :func:`collections_at_validations`)."""
    gc.collect()


class TimeBudgetControl:
    """The trainer's time budget (``self.budget``: a :class:`~dope_hope.training.budget.BudgetPlan`,
    None without a time limit): the clock, the speed, the plans and the end they set."""

    @property
    def budget_sets_horizon(self) -> bool:
        """Whether the time budget's plans set the schedule's end (a time limit without steps)."""
        return self.budget is not None and not self.ts["steps"]

    @property
    def planned_steps(self) -> int | None:
        """The step the time budget's last plan ends the run at (None before a plan / without)."""
        return None if self.budget is None or self.budget.last is None else int(self.budget.last["end"])

    def elapsed(self) -> float:
        """Seconds since this process's trainer started (by its clock)."""
        return self.clock() - self._t0

    def budget_used(self) -> float:
        """Seconds of the time budget used: earlier processes' (up to their last checkpoint)
        plus this one's."""
        return self._time_used_before + self.elapsed()

    def _budget_step(self, validated: bool = False) -> None:
        """Time-limited run, after each step (``validated``: after a validation): rank 0
        measures the speed and plans when a plan is due (:meth:`_decide_end`); every rank
        takes the end it planned."""
        if self.budget is None or self.step >= self.total_steps:
            return
        end = self._broadcast_end(self._decide_end(validated) if self.dist.main else None)
        if end is not None:
            self._set_end(end)

    def _broadcast_end(self, end: int | None) -> int | None:
        """Rank 0's end step (or None) on every rank."""
        if not self.dist.active:
            return end
        t = torch.tensor([-1 if end is None else end], dtype=torch.int64, device=self.device if self.cuda else "cpu")
        dist.broadcast(t, 0)
        return None if int(t.item()) < 0 else int(t.item())

    def _set_end(self, end: int) -> None:
        """End the run at step ``end``; the cosine or wsd's decay (when the budget sets it) falls to it."""
        if end != self.total_steps and self.budget_sets_horizon:
            self.lr_lambda.replan(self.step, max(self.step + 1, end))
        self.total_steps = end

    def other_time(self) -> float:
        """Seconds of the budget not spent on steps: validations and each process's start-up
        (every process so far)."""
        return self._other_before + self._startup_s + self._val_time_run

    def _first_window_speed(self) -> tuple[float | None, int]:
        """Seconds per step of this process's steps since its speed window started
        (validation time left out) and the number of those steps; (None, 0) before."""
        if self._window is None:
            return None, 0
        t, val, n = self._window
        steps = self._steps_this_run - n
        if steps <= 0:
            return None, 0
        return max(1e-9, (self.clock() - t - (self._val_time_run - val)) / steps), steps

    def _recent_speed(self, last: dict[str, Any]) -> float:
        """Seconds per step since the last plan (budget used minus validations and start-ups,
        over the steps: the same figures whichever process made them, so a resumed run measures what an
        uninterrupted one does); since an earlier plan when the last is fewer than
        MIN_WINDOW_STEPS steps back, the first plan's figure when all are."""
        since = next((p for p in reversed(self.budget.plans) if self.step - int(p["step"]) >= MIN_WINDOW_STEPS), None)
        if since is None:
            return float(self.budget.plans[0]["per_step_s"]) if self.budget.plans else float(last["per_step_s"])
        train_s = (self.budget_used() - self.other_time()) - (float(since["used_s"]) - float(since.get("other_s", 0.0)))
        return max(1e-9, train_s / (self.step - int(since["step"])))

    def _val_cost(self, per_step: float) -> float:
        """Seconds a validation (best.pt and plots included) costs at ``per_step`` seconds per
        step: the median of the last three validations, in training steps of their time (a
        load that slows the steps slows the validation too), else an estimate: a batch costs
        about a training step per unit of image area (forward + decoding of whole frames vs
        forward + backward of the training crops)."""
        if self._val_steps:
            return float(np.median(self._val_steps[-3:])) * per_step
        if int(self.ts["val_every"]) <= 0:
            return 0.0
        val_batches = math.ceil(len(self.val_set) / max(1, int(self.ts["val_batch_size"] or self.batch_size)))
        h, w = input_hw(self.config)
        crop = self.train_set.augment.crop or (h, w)
        return per_step * val_batches * max(1.0, h * w / (crop[0] * crop[1]))

    def _after_run_cost(self, val_s: float) -> float:
        """Seconds the run spends after its final validation, which costs ``val_s``: choosing
        the thresholds (:meth:`Trainer._calibrate`), estimated from
        :data:`CALIBRATION_IN_VALIDATIONS` and the run's objects; 0 without it."""
        fixed, per_object = CALIBRATION_IN_VALIDATIONS
        return (fixed + per_object * len(self.objects)) * val_s if self.calibrates else 0.0

    def _decide_end(self, validated: bool) -> int | None:
        """Rank 0: the new end step when a plan is due or the budget is spent, else None.

        The first plan measures this process's steps from its first one, and again once the
        batches the loader fetched ahead are used up (they come for free: counting them makes a
        loader-bound run look faster than it is); re-plans measure the steps since the last plan.
        """
        last = self.budget.last
        used = self.budget_used()
        if last is None:
            n = self._steps_this_run
            steady = 1 + int(self.ts["workers"]) * LOADER_PREFETCH
            if not validated and n in (1, steady):
                self._window = (self.clock(), self._val_time_run, n)
            measured, window_steps = self._first_window_speed()
            if validated and measured:
                self._val_steps.append(self._val_seconds / measured)
            if used + self._val_seconds + self._after_run_cost(self._val_seconds) >= self.budget.limit_s:
                # the final validation (and the thresholds' choice) would not fit
                return self._plan_now("budget spent before a plan", per_step=measured or 0.0, end=self.step)
            if measured is None or (window_steps < int(self.ts["horizon_estimate_after"]) and not validated):
                return None
            return self._plan_now("first", per_step=measured)
        per_step = self._recent_speed(last)
        if validated:
            self._val_steps.append(self._val_seconds / per_step)
        every = int(self.ts["val_every"]) * self.steps_per_epoch
        val_cost = self._val_cost(per_step)
        if not self.budget.one_more_fits(self.step, used, per_step, val_cost, every, validated,
                                         self._after_run_cost(val_cost)):
            return self._plan_now("budget spent", per_step=per_step, end=self.step)
        if validated or self.budget.due(used, self.step):
            return self._plan_now("validation" if validated else "re-plan", per_step=per_step, validated=validated)
        return None

    def _plan_now(self, why: str, per_step: float | None = None, end: int | None = None,
                  validated: bool = False) -> int:
        """Record a plan from ``per_step`` (default: the last plan's) or, given ``end``, the
        end itself; return the end step."""
        last = self.budget.last
        per_step = float(last["per_step_s"]) if per_step is None and last is not None else float(per_step or 0.0)
        val_cost = self._val_cost(per_step)
        used = self.budget_used()
        if end is None:
            every = int(self.ts["val_every"]) * self.steps_per_epoch
            plan = self.budget.plan(self.step, used, self.other_time(), per_step, val_cost, every, self._nominal_total, why,
                                    validated, self._after_run_cost(val_cost))
        else:
            plan = make_plan(self.step, end, end, per_step, val_cost, used, self.other_time(), why)
            self.budget.plans.append(plan)
        if self.dist.main:
            level = logging.DEBUG if why in ("re-plan", "validation") else logging.INFO
            log.log(level, "time budget %.3g min (%s): the run ends at step %d (%.3f s per step, %.1f s of the "
                    "budget used by step %d)", self.budget.limit_s / 60.0, why, plan["end"], per_step, used, self.step)
        self._set_end(plan["end"])
        return int(plan["end"])
