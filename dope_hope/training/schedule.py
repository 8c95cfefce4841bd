"""Learning-rate schedule: ``constant | cosine | step`` with linear warm-up, as a LambdaLR factor.

The horizon is the total number of steps (or, under a time limit without an explicit
step/epoch count, an estimate from the measured speed that is refined after every epoch, so
that the cosine reaches its floor when time runs out).
"""
from __future__ import annotations

import math


# =============================================================================== schedule
class LrLambda:
    """Picklable lr factor of step: linear warm-up, then constant / cosine / step decay.

    ``horizon`` (total steps) may be updated while training (time-limited runs); it is part
    of the scheduler's state dict, so a resumed run continues with the same schedule.
    """

    def __init__(self, kind: str, horizon: int, warmup: int = 0, min_factor: float = 0.01,
                 step_every: int = 1000, gamma: float = 0.1):
        self.kind, self.horizon, self.warmup = kind, int(max(1, horizon)), int(warmup)
        self.min_factor, self.step_every, self.gamma = float(min_factor), int(max(1, step_every)), float(gamma)

    def __call__(self, step: int) -> float:
        if self.warmup > 0 and step < self.warmup:
            return (step + 1) / self.warmup
        if self.kind == "cosine":
            span = max(1, self.horizon - self.warmup)
            p = min(1.0, (step - self.warmup) / span)
            return self.min_factor + (1 - self.min_factor) * 0.5 * (1 + math.cos(math.pi * p))
        if self.kind == "step":
            return self.gamma ** (step // self.step_every)
        return 1.0
