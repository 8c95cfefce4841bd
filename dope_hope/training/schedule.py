"""Learning-rate schedule: ``constant | cosine | step | wsd`` with linear warm-up, as a LambdaLR factor.

The horizon is the total number of steps. A run whose length changes while it trains (a time
budget re-planned from the measured speed, ``--steps`` changed at a resume) calls
:meth:`LrLambda.replan`: from that step the cosine (or the decay of ``wsd``) reaches its floor
at the new end, and the learning rate never jumps.

``wsd`` (warm-up, stable, decay; Hägele et al. 2024, "Scaling Laws and Compute-Optimal Training
Beyond Fixed Training Durations"): the peak rate until the last ``decay_share`` of the planned
steps after the warm-up, then a straight line to the floor at the end. The decay's start is
read from the plan in force, so re-plans in the stable part change nothing, and a re-plan
during the decay goes on from the factor reached (held until the new plan's decay starts).

How a cosine goes on at a re-plan (``train.cosine_replan``):

- ``restart`` (the default): a new cosine from the factor it had reached, from its flat top.
  A time budget re-plans at every validation and as the speed changes (about thirty times in
  30 minutes of the lite recipe), and each re-plan flattens the curve again: the learning rate
  stays near its peak for most of the run and falls in its last tenth (at 92 % of a 30-minute
  run 43 % of the peak, where one cosine is at 4 %). The better of the two for a 30-minute
  Ketchup model so far (one run each, bench/RESULTS.md "End-to-end accuracy").
- ``continue``: the cosine goes on from the phase it had reached, so a run anneals as one
  cosine over the steps it makes, and a re-plan that keeps the end changes nothing.

**A finished run trained on** (a longer ``--time-budget``, ``--steps`` or ``--epochs`` at
``--resume``; :meth:`LrLambda.restart`): its rate had reached the floor, so a re-plan "from
where it is" would keep it there for the whole continuation (a 30-minute Ketchup run continued
to 60 and 120 minutes trained at 0.02 of the peak and gained nothing: bench/EXPERIMENTS.md
"Training curve"). It restarts warm instead (SGDR, Loshchilov & Hutter 2017, "SGDR: Stochastic
Gradient Descent with Warm Restarts"): the warm-up's steps up from the floor to the peak, then
the decay to the floor at the new end. Each segment ``(start, end, top, ramp)`` carries its own
warm-up ``ramp`` (0: none; a 3-tuple from an older checkpoint reads as 0).
"""
from __future__ import annotations

import math


# =============================================================================== schedule
class LrLambda:
    """Picklable lr factor of step: linear warm-up, then constant / cosine / step / wsd decay.

    ``horizon`` is the first planned length; ``segments`` the re-plans ``(start step, end
    step, factor at start)``. Both are part of the scheduler's state dict, so a resumed run
    continues with the same schedule.
    """

    #: The kinds whose decay follows :meth:`replan` (the others ignore the run's end).
    REPLANNED = ("cosine", "wsd")

    def __init__(self, kind: str, horizon: int, warmup: int = 0, min_factor: float = 0.01,
                 step_every: int = 1000, gamma: float = 0.1, replan_mode: str = "restart",
                 decay_share: float = 0.2):
        self.kind, self.horizon, self.warmup = kind, int(max(1, horizon)), int(warmup)
        self.replan_mode, self.decay_share = replan_mode, float(decay_share)
        self.min_factor, self.step_every, self.gamma = float(min_factor), int(max(1, step_every)), float(gamma)
        self.segments: list[tuple[int, int, float]] = []

    def replan(self, step: int, end: int) -> None:
        """From ``step`` on, the cosine (or wsd's decay) falls from its present factor to the
        floor at ``end``, as the module docstring says; earlier steps keep their factors, and a
        re-plan during the warm-up (the first, or a restart's) starts at its end."""
        start = max(int(step), self.warmup)
        seg_start, _, top, ramp = self._segment_at(start)
        if ramp and start < seg_start + ramp:  # a restart's warm-up: it goes on to the new end
            self.segments = [seg for seg in self.segments if seg[0] < seg_start] + [(seg_start, int(end), top, ramp)]
            return
        factor = self(start)
        self.segments = [seg for seg in self.segments if seg[0] < start] + [(start, int(end), float(factor), 0)]

    def restart(self, step: int, end: int) -> None:
        """A warm restart at ``step`` (module docstring): ``warmup`` steps up to the peak, then
        the decay to the floor at ``end``; earlier steps keep their factors."""
        start = int(step)
        self.segments = [seg for seg in self.segments if seg[0] < start] + [(start, int(end), 1.0, self.warmup)]

    def ended(self, step: int) -> bool:
        """Whether ``step`` is at or past the end of the plan in force (its rate at the floor)."""
        return self.kind in self.REPLANNED and step >= self._segment_at(step)[1]

    def _segment_at(self, step: int) -> tuple[int, int, float, int]:
        """The plan in force at ``step``: (start, end, top factor, warm-up steps)."""
        plan = (self.warmup, self.horizon, 1.0, 0)
        for seg in self.segments:  # the last re-plan at or before `step`
            if seg[0] <= step:
                plan = (int(seg[0]), int(seg[1]), float(seg[2]), int(seg[3]) if len(seg) > 3 else 0)
        return plan

    def __call__(self, step: int) -> float:
        if self.warmup > 0 and step < self.warmup:
            return (step + 1) / self.warmup
        if self.kind in self.REPLANNED:
            start, end, top, ramp = self._segment_at(step)
            if ramp and step < start + ramp:  # a restart's warm-up, from the floor
                return self.min_factor + (top - self.min_factor) * (step - start + 1) / ramp
            start += ramp
            if self.kind == "wsd":
                return self._wsd(step, start, end, top)
            p = min(1.0, (step - start) / max(1, end - start))
            if self.replan_mode == "continue":
                phase = self._phase(top)
                p, top = phase + (1.0 - phase) * p, 1.0
            return self.min_factor + (top - self.min_factor) * 0.5 * (1 + math.cos(math.pi * p))
        if self.kind == "step":
            return self.gamma ** (step // self.step_every)
        return 1.0

    def _wsd(self, step: int, start: int, end: int, top: float) -> float:
        """wsd's factor at ``step`` under the plan ``(start, end, top)``: ``top`` until the
        decay starts (the last ``decay_share`` of the steps from the warm-up's end to ``end``),
        then linear to the floor at ``end``."""
        decay_from = max(start, end - round(self.decay_share * max(0, end - self.warmup)))
        if step < decay_from:
            return top
        p = min(1.0, (step - decay_from) / max(1, end - decay_from))
        return top + (self.min_factor - top) * p

    def _phase(self, factor: float) -> float:
        """The cosine's phase in [0, 1] at which it gives ``factor`` (a re-plan's recorded
        factor at its start; 1.0: phase 0)."""
        span = 1.0 - self.min_factor
        if span <= 0:
            return 0.0
        return math.acos(min(1.0, max(-1.0, 2.0 * (factor - self.min_factor) / span - 1.0))) / math.pi
