"""Learning-rate schedule: ``constant | cosine | step`` with linear warm-up, as a LambdaLR factor.

The horizon is the total number of steps. A run whose length changes while it trains (a time
budget re-planned from the measured speed, ``--steps`` changed at a resume) calls
:meth:`LrLambda.replan`: from that step the cosine falls from the factor it had reached to its
floor at the new end, so the learning rate never jumps.
"""
from __future__ import annotations

import math


# =============================================================================== schedule
class LrLambda:
    """Picklable lr factor of step: linear warm-up, then constant / cosine / step decay.

    ``horizon`` is the first planned length; ``segments`` the re-plans ``(start step, end
    step, factor at start)``. Both are part of the scheduler's state dict, so a resumed run
    continues with the same schedule.
    """

    def __init__(self, kind: str, horizon: int, warmup: int = 0, min_factor: float = 0.01,
                 step_every: int = 1000, gamma: float = 0.1):
        self.kind, self.horizon, self.warmup = kind, int(max(1, horizon)), int(warmup)
        self.min_factor, self.step_every, self.gamma = float(min_factor), int(max(1, step_every)), float(gamma)
        self.segments: list[tuple[int, int, float]] = []

    def replan(self, step: int, end: int) -> None:
        """From ``step`` on, the cosine falls from its present factor to the floor at ``end``
        (earlier steps keep their factors; a re-plan during the warm-up starts at its end)."""
        start = max(int(step), self.warmup)
        factor = self(start)
        self.segments = [seg for seg in self.segments if seg[0] < start] + [(start, int(end), float(factor))]

    def __call__(self, step: int) -> float:
        if self.warmup > 0 and step < self.warmup:
            return (step + 1) / self.warmup
        if self.kind == "cosine":
            start, end, top = self.warmup, self.horizon, 1.0
            for seg in self.segments:  # the last re-plan at or before `step`
                if seg[0] <= step:
                    start, end, top = seg
            p = min(1.0, (step - start) / max(1, end - start))
            return self.min_factor + (top - self.min_factor) * 0.5 * (1 + math.cos(math.pi * p))
        if self.kind == "step":
            return self.gamma ** (step // self.step_every)
        return 1.0
