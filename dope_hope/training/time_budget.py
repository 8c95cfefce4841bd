"""The time of a training run and its budget: the clock (the budget belongs to the run: the
time of every process so far), the speed measured from the steps, the plans of
:mod:`~dope_hope.training.budget` turning the budget left into the step the run ends at,
re-planned at every validation and whenever a share of the budget has passed, and the stop
when one more step and the final validation would not fit. The garbage collector's full passes
are held to the validations (:func:`collections_at_validations`), so that a validation's cost,
which the plans count, does not jump at random.

:class:`TimeBudget` is fed what it measures by the trainer (its start, each step, each
validation's seconds) and given the shape of the run once (:class:`BudgetShape`); asked after a
step, it answers with the step the run ends at (:meth:`TimeBudget.decide_end`), which the
trainer then follows (its step count and the schedule's end).
"""
from __future__ import annotations

import contextlib
import gc
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from dope_hope.training.budget import MIN_WINDOW_STEPS, BudgetPlan, make_plan

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


@dataclass(frozen=True)
class BudgetShape:
    """What a run tells its time budget once, at its start.

    Attributes:
        limit_s: the budget, seconds; None: no time limit (the budget only keeps the time).
        sets_horizon: whether the plans set the schedule's end (a time limit without
            ``train.steps``).
        nominal_steps: the run's length without the budget (steps or epochs), steps.
        steps_per_epoch: optimizer steps per epoch.
        val_every: epochs between validations (0: none).
        val_batches: batches of one validation.
        val_area_ratio: a validation frame's area over a training crop's (at least 1): a
            validation batch costs about that many training steps.
        first_window_steps: the step after which the loader's prefetched batches are used up
            (1 + workers x :data:`LOADER_PREFETCH`): the first plan's speed window starts again there.
        horizon_estimate_after: steps the first plan measures.
        after_run_validations: what the run does after its final validation (the thresholds'
            choice), in validations of the same frames; None: nothing.
    """

    limit_s: float | None
    sets_horizon: bool
    nominal_steps: int
    steps_per_epoch: int
    val_every: int
    val_batches: int
    val_area_ratio: float
    first_window_steps: int
    horizon_estimate_after: int
    after_run_validations: float | None

    @property
    def val_every_steps(self) -> int:
        """Steps between validations (0: none)."""
        return self.val_every * self.steps_per_epoch


def after_run_validations(calibrates: bool, objects: int) -> float | None:
    """The thresholds' choice at a run's end in validations (:data:`CALIBRATION_IN_VALIDATIONS`),
    for a run of ``objects`` objects that ``calibrates``; None when it does not."""
    fixed, per_object = CALIBRATION_IN_VALIDATIONS
    return fixed + per_object * objects if calibrates else None


class TimeBudget:
    """A run's time (its clock, the time of earlier processes, this one's start-up and
    validations) and, under a time limit, its plans (``plan``: a
    :class:`~dope_hope.training.budget.BudgetPlan`, None without one).

    Args:
        shape: the run's shape (:class:`BudgetShape`).
        clock: the seconds the budget counts (``time.monotonic``, or an injected clock).
        started: the clock's reading when the budget started (the command's start).
    """

    def __init__(self, shape: BudgetShape, clock: Callable[[], float], started: float):
        self.shape = shape
        self.clock = clock
        self.started = started
        self.plan = BudgetPlan(shape.limit_s) if shape.limit_s is not None else None
        self.used_before = 0.0  # seconds of earlier processes (up to their last checkpoint)
        self.other_before = 0.0  # of them not spent on steps (validations, start-ups)
        self.startup_s = 0.0  # this process's seconds before its first step
        self.val_seconds = 0.0  # the last validation's seconds (plots included)
        self.val_steps: list[float] = []  # the validations' seconds over the seconds per step then (rank 0)
        self.val_time_run = 0.0  # all validations' seconds, this process
        self.steps_this_run = 0
        self.window: tuple[float, float, int] | None = None  # first plan's window: (clock, val time, steps)

    # ------------------------------------------------------------------ what the trainer feeds it
    def begin_steps(self) -> None:
        """The first step starts now: the seconds so far are this process's start-up."""
        self.startup_s = self.elapsed()

    def stepped(self) -> None:
        """One optimizer step of this process is done."""
        self.steps_this_run += 1

    def validated(self, seconds: float) -> None:
        """A validation (best.pt and plots included) took ``seconds``."""
        self.val_seconds = seconds
        self.val_time_run += seconds

    def state(self) -> dict[str, Any]:
        """What a checkpoint records of the budget (:meth:`restore` reads it back)."""
        return {"time_used_s": self.used(), "other_s": self.other_time(), "last_val_s": self.val_seconds,
                "val_steps": self.val_steps[-3:], "planned_steps": self.planned_steps,
                "plans": self.plan.plans if self.plan is not None else None}

    def restore(self, extra: dict[str, Any]) -> None:
        """The time a checkpoint's ``extra`` records as used before and its validations' costs
        (its plans are the trainer's to take up or replace: a length or budget changed at the
        resume plans again)."""
        self.used_before = float(extra.get("time_used_s", 0.0))
        self.other_before = float(extra.get("other_s", 0.0))
        self.val_seconds = float(extra.get("last_val_s", 0.0))
        self.val_steps = [float(v) for v in extra.get("val_steps") or []]

    # ------------------------------------------------------------------ the time
    def elapsed(self) -> float:
        """Seconds since this process's budget started (by its clock)."""
        return self.clock() - self.started

    def used(self) -> float:
        """Seconds of the time budget used: earlier processes' (up to their last checkpoint)
        plus this one's."""
        return self.used_before + self.elapsed()

    def other_time(self) -> float:
        """Seconds of the budget not spent on steps: validations and each process's start-up
        (every process so far)."""
        return self.other_before + self.startup_s + self.val_time_run

    @property
    def planned_steps(self) -> int | None:
        """The step the last plan ends the run at (None before a plan / without a limit)."""
        return None if self.plan is None or self.plan.last is None else int(self.plan.last["end"])

    @property
    def end_rests_on_estimate(self) -> bool:
        """Whether the last plan's end was set from an estimated validation cost (no validation
        measured yet): a run that reaches that end validates, then plans again from the
        measured cost, which may move the end later (the estimate scales the step time, and the
        first steps of a run whose loader decodes every frame once are far slower than its
        validation)."""
        last = None if self.plan is None else self.plan.last
        return last is not None and not last.get("val_measured", True)

    # ------------------------------------------------------------------ the plans
    def _first_window_speed(self) -> tuple[float | None, int]:
        """Seconds per step of this process's steps since its speed window started
        (validation time left out) and the number of those steps; (None, 0) before."""
        if self.window is None:
            return None, 0
        t, val, n = self.window
        steps = self.steps_this_run - n
        if steps <= 0:
            return None, 0
        return max(1e-9, (self.clock() - t - (self.val_time_run - val)) / steps), steps

    def _recent_speed(self, step: int, last: dict[str, Any]) -> float:
        """Seconds per step since the last plan (budget used minus validations and start-ups,
        over the steps: the same figures whichever process made them, so a resumed run measures what an
        uninterrupted one does); since an earlier plan when the last is fewer than
        MIN_WINDOW_STEPS steps back, the first plan's figure when all are."""
        since = next((p for p in reversed(self.plan.plans) if step - int(p["step"]) >= MIN_WINDOW_STEPS), None)
        if since is None:
            first = self.plan.plans[0] if self.plan.plans else last
            return max(1e-9, float(first["per_step_s"]))
        train_s = (self.used() - self.other_time()) - (float(since["used_s"]) - float(since.get("other_s", 0.0)))
        return max(1e-9, train_s / (step - int(since["step"])))

    def _val_cost(self, per_step: float) -> float:
        """Seconds a validation (best.pt and plots included) costs at ``per_step`` seconds per
        step: the median of the last three validations, in training steps of their time (a
        load that slows the steps slows the validation too), else an estimate: a batch costs
        about a training step per unit of image area (forward + decoding of whole frames vs
        forward + backward of the training crops)."""
        if self.val_steps:
            return float(np.median(self.val_steps[-3:])) * per_step
        if self.shape.val_every <= 0:
            return 0.0
        return per_step * self.shape.val_batches * self.shape.val_area_ratio

    def _after_run_cost(self, val_s: float) -> float:
        """Seconds the run spends after its final validation, which costs ``val_s``: choosing
        the thresholds (:class:`~dope_hope.training.calibration.RunThresholds`); 0 without it."""
        factor = self.shape.after_run_validations
        return factor * val_s if factor is not None else 0.0

    def decide_end(self, step: int, validated: bool) -> int | None:
        """Rank 0, after step ``step`` (``validated``: after a validation) of a time-limited
        run: the new end step when a plan is due or the budget is spent, else None.

        The first plan measures this process's steps from its first one, and again once the
        batches the loader fetched ahead are used up (they come for free: counting them makes a
        loader-bound run look faster than it is); re-plans measure the steps since the last plan.
        """
        last = self.plan.last
        used = self.used()
        if last is None:
            n = self.steps_this_run
            if not validated and n in (1, self.shape.first_window_steps):
                self.window = (self.clock(), self.val_time_run, n)
            measured, window_steps = self._first_window_speed()
            if validated and measured:
                self.val_steps.append(self.val_seconds / measured)
            if used + self.val_seconds + self._after_run_cost(self.val_seconds) >= self.plan.limit_s:
                # the final validation (and the thresholds' choice) would not fit
                return self.plan_now(step, "budget spent before a plan", per_step=measured or 0.0, end=step,
                                     val_measured=True)  # spent on what was measured: no estimate
            if measured is None or (window_steps < self.shape.horizon_estimate_after and not validated):
                return None
            return self.plan_now(step, "first", per_step=measured)
        per_step = self._recent_speed(step, last)
        if validated:
            self.val_steps.append(self.val_seconds / per_step)
        every = self.shape.val_every_steps
        val_cost = self._val_cost(per_step)
        if not self.plan.one_more_fits(step, used, per_step, val_cost, every, validated,
                                       self._after_run_cost(val_cost)):
            return self.plan_now(step, "budget spent", per_step=per_step, end=step)
        if validated or self.plan.due(used, step):
            return self.plan_now(step, "validation" if validated else "re-plan", per_step=per_step,
                                 validated=validated)
        return None

    def plan_now(self, step: int, why: str, per_step: float | None = None, end: int | None = None,
                 validated: bool = False, val_measured: bool | None = None) -> int:
        """Rank 0: record a plan made after step ``step`` from ``per_step`` seconds per step
        (default: the last plan's) or, given ``end``, the end itself; return the end step.
        ``val_measured``: whether the plan rests on measured validations (default: whether
        this run measured one)."""
        last = self.plan.last
        per_step = float(last["per_step_s"]) if per_step is None and last is not None else float(per_step or 0.0)
        val_cost = self._val_cost(per_step)
        used = self.used()
        measured = bool(self.val_steps) if val_measured is None else val_measured
        if end is None:
            plan = self.plan.plan(step, used, self.other_time(), per_step, val_cost, self.shape.val_every_steps,
                                  self.shape.nominal_steps, why, validated, self._after_run_cost(val_cost), measured)
        else:
            plan = make_plan(step, end, end, per_step, val_cost, used, self.other_time(), why, measured)
            self.plan.plans.append(plan)
        level = logging.DEBUG if why in ("re-plan", "validation") else logging.INFO
        log.log(level, "time budget %.3g min (%s): the run ends at step %d (%.3f s per step, %.1f s of the "
                "budget used by step %d)", self.plan.limit_s / 60.0, why, plan["end"], per_step, used, step)
        return int(plan["end"])
