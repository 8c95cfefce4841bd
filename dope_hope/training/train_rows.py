"""The progress bar of a training run and the train rows of its metrics.csv."""
from __future__ import annotations

import time

from tqdm import tqdm

from dope_hope.training.metrics_log import MetricsLog


class TrainRows:
    """The progress bar and the train rows of metrics.csv: one row is the mean loss of the
    steps since the previous row (the trainer writes one every log_every steps, before each
    validation and at the end, so that short runs have rows).

    Args:
        metrics: the run's metrics log.
        total_steps: the bar's length, steps; initial_step: where it starts (a resumed run).
        show: draw the bar (rank 0, progress on).
        images_per_step: images of one step over all processes (images/s).
        writes: whether this process writes rows (rank 0).
    """

    def __init__(self, metrics: MetricsLog, total_steps: int, initial_step: int, show: bool,
                 images_per_step: int, writes: bool):
        self.metrics = metrics
        self.images_per_step = images_per_step
        self.writes = writes
        self.bar = tqdm(total=total_steps, initial=initial_step, disable=not show,
                        unit="step", dynamic_ncols=True, desc="train")
        self.restart_clock()

    def restart_clock(self) -> None:
        """images/s counts this process's steps from here."""
        self.t0, self.steps = time.monotonic(), 0

    def stepped(self) -> None:
        """One more step of this process."""
        self.steps += 1
        self.bar.update(1)

    def follow_total(self, total_steps: int) -> None:
        """The bar's total follows a re-planned step count."""
        if self.bar.total != total_steps:
            self.bar.total = total_steps

    def row(self, step: int, epoch: int, lr: float, loss: float, time_s: float) -> None:
        """A train row (rank 0; ``loss``: the mean since the last row, ``time_s``: the budget's
        seconds used), then images/s counts again from here."""
        if self.writes:
            ips = self.steps * self.images_per_step / max(time.monotonic() - self.t0, 1e-9)
            self.metrics.write("train", step=step, epoch=epoch, lr=lr, loss=loss,
                               images_per_s=round(ips, 2), time_s=time_s)
            self.bar.set_postfix(loss=f"{loss:.4f}", lr=f"{lr:.2e}", img_s=f"{ips:.1f}")
        self.restart_clock()

    def close(self) -> None:
        self.bar.close()
