"""A time budget turned into the step a training run ends at, re-planned as the speed changes.

The trainer measures the seconds per step of the recent steps (validation time left out) and
asks :class:`BudgetPlan` for the end step: first once the speed is known, then again at every
validation and whenever a share of the budget has passed since the last plan (the share
shrinks as the end approaches), and at every step it checks that one more step still fits.
Each plan is a plain dict (:func:`make_plan`) kept in the checkpoint, so a resumed run
continues with the plans made before the interruption (the learning rate followed them; see
:meth:`dope_hope.training.schedule.LrLambda.replan`) and plans again from its own
measurements.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

#: Share of the budget kept free at the end (the last checkpoint, summary, what the speed
#: estimate misses): the run plans to end at 98.5 % of its budget.
END_MARGIN = 0.015
#: A re-plan is due when this share of the budget, or a quarter of what is left (whichever is
#: less), has passed since the last plan, or half of the steps it planned (a run that speeds up
#: re-plans before it reaches an end planned at the slower speed).
REPLAN_SHARE = 0.05
#: Steps a re-plan's speed window needs; fewer (just after a resume) reuse the last plan's speed.
MIN_WINDOW_STEPS = 5


def make_plan(step: int, end: int, budget_end: int, per_step_s: float, val_s: float, used_s: float,
              other_s: float, why: str, val_measured: bool = True) -> dict[str, Any]:
    """One plan: made after ``step`` steps with ``used_s`` seconds of the budget used
    (``other_s`` of them not by steps: validations, each process's start), from ``per_step_s`` seconds per step and ``val_s``
    per validation (``val_measured``: from validations this run made, else an estimate); the
    budget allows ``budget_end`` steps, the run ends at ``end`` (<= its nominal length); ``why`` in words."""
    return {"step": int(step), "end": int(end), "budget_end": int(budget_end), "per_step_s": float(per_step_s),
            "val_s": float(val_s), "used_s": float(used_s), "other_s": float(other_s), "why": str(why),
            "val_measured": bool(val_measured)}


@dataclass
class BudgetPlan:
    """The plans of one time-limited run (``limit_s`` seconds of budget).

    Attributes:
        limit_s: the budget in seconds.
        plans: every plan so far, oldest first (:func:`make_plan` dicts; checkpointed).
    """

    limit_s: float
    plans: list[dict[str, Any]] = field(default_factory=list)

    @property
    def last(self) -> dict[str, Any] | None:
        return self.plans[-1] if self.plans else None

    def due(self, used_s: float, step: int) -> bool:
        """Whether a re-plan is due after ``step`` steps and ``used_s`` seconds (a first plan
        always is)."""
        last = self.last
        if last is None:
            return True
        halfway = max(MIN_WINDOW_STEPS, (last["end"] - last["step"]) // 2)
        since = used_s - last["used_s"]
        return (step - last["step"] >= halfway
                or since >= min(REPLAN_SHARE * self.limit_s, 0.25 * max(0.0, self.limit_s - used_s)))

    @staticmethod
    def run_cost(step: int, end: int, per_step_s: float, val_s: float, val_every_steps: int,
                 validated: bool = False, after_s: float = 0.0) -> float:
        """Seconds from ``step`` to the end of a run that ends at ``end``: its steps and its
        validations, at the multiples of ``val_every_steps`` (0: none) after ``step`` (and at
        ``step`` unless ``validated`` there already), the last one before a run's end skipped
        when the run ends before the next (the final validation, at ``end``, replaces it),
        and ``after_s``, what the run does after its final validation (the thresholds' choice)."""
        seconds = (end - step) * per_step_s + after_s
        lo = step if validated else step - 1
        if val_every_steps <= 0 or end <= lo:
            return seconds
        count = end // val_every_steps - lo // val_every_steps  # multiples in (lo, end]
        return seconds + val_s * (count if end % val_every_steps == 0 else max(1, count))

    def budget_steps(self, step: int, used_s: float, per_step_s: float, val_s: float, val_every_steps: int,
                     validated: bool = False, after_s: float = 0.0) -> int:
        """The last step the budget allows: the largest end whose :meth:`run_cost` (which grows
        with the end) fits in the time left before the end margin; ``step`` when none does."""
        left = self.limit_s * (1.0 - END_MARGIN) - used_s
        per = max(per_step_s, 1e-9)
        lo, hi = step, step + math.ceil(max(0.0, left) / per) + 1  # the cost of hi exceeds left
        while hi - lo > 1:
            mid = (lo + hi) // 2
            fits = self.run_cost(step, mid, per, val_s, val_every_steps, validated, after_s) <= left
            lo, hi = (mid, hi) if fits else (lo, mid)
        return lo

    def plan(self, step: int, used_s: float, other_s: float, per_step_s: float, val_s: float,
             val_every_steps: int, nominal_end: int, why: str, validated: bool = False,
             after_s: float = 0.0, val_measured: bool = True) -> dict[str, Any]:
        """Make, record and return a plan (its ``end`` never before ``step``)."""
        budget_end = self.budget_steps(step, used_s, per_step_s, val_s, val_every_steps, validated, after_s)
        plan = make_plan(step, max(step, min(nominal_end, budget_end)), budget_end, per_step_s, val_s, used_s,
                         other_s, why, val_measured)
        self.plans.append(plan)
        return plan

    def one_more_fits(self, step: int, used_s: float, per_step_s: float, val_s: float, val_every_steps: int,
                      validated: bool = False, after_s: float = 0.0) -> bool:
        """Whether a run ending one step later (validations included) fits in the budget, half
        the end margin kept free (for what the estimates miss)."""
        cost = self.run_cost(step, step + 1, per_step_s, val_s, val_every_steps, validated, after_s)
        return used_s + cost <= self.limit_s * (1.0 - END_MARGIN / 2)
