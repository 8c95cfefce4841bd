"""Per-step and per-epoch training metrics: ``metrics.csv`` and ``metrics.jsonl`` in the run folder.

With the optional ``tensorboard`` package (``pip install dope-hope[tensorboard]``) the same
scalars, and the validation snapshots, also go to ``RUN/tensorboard`` (``tensorboard --logdir RUN``).
"""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

from dope_hope.io.atomic import atomic_write_text, write_error


class MetricsLog:
    """Scalars to ``metrics.csv`` + ``metrics.jsonl`` (+ TensorBoard when installed); rank 0.

    ``keep_rows``: the rows the checkpoint being resumed had logged (``rows`` when it was
    written); later rows belong to steps the resumed run does again and are dropped, so a
    resumed run's files equal an uninterrupted run's. A fresh run starts empty files.
    """

    COLUMNS = ("event", "step", "epoch", "time_s", "lr", "loss", "images_per_s",
               "val_loss", "val_kp_acc", "val_kp_acc_decoded")

    def __init__(self, out: Path, enabled: bool, keep_rows: int = 0, purge_step: int | None = None):
        self.enabled = enabled
        self.out = out
        self.tb = None
        self.rows = 0
        if not enabled:
            return
        self.csv_path = out / "metrics.csv"
        self.jsonl_path = out / "metrics.jsonl"
        self.rows = self._truncate(keep_rows)
        try:
            from torch.utils.tensorboard import SummaryWriter  # noqa: PLC0415 (TensorBoard is optional (the tensorboard extra))
            self.tb = SummaryWriter(str(out / "tensorboard"), purge_step=purge_step)
        except ImportError:  # tensorboard is optional
            self.tb = None

    def _truncate(self, keep: int) -> int:
        """Keep the header and the first ``keep`` rows of both files; returns the rows kept."""
        def head(path: Path, n: int) -> list[str]:
            try:
                return path.read_text(encoding="utf-8").splitlines(keepends=True)[:n]
            except (OSError, UnicodeDecodeError):
                return []

        rows = head(self.jsonl_path, keep) if keep else []
        csv_rows = head(self.csv_path, keep + 1)[1:] if keep else []
        n = min(len(rows), len(csv_rows))
        buf = io.StringIO()
        csv.writer(buf).writerow(self.COLUMNS)
        atomic_write_text(self.csv_path, buf.getvalue() + "".join(csv_rows[:n]))
        atomic_write_text(self.jsonl_path, "".join(rows[:n]))
        return n

    def write(self, event: str, **values: Any) -> None:
        if not self.enabled:
            return

        row = {"event": event, **values}
        for path, text in ((self.csv_path, None), (self.jsonl_path, json.dumps(row) + "\n")):
            try:
                with path.open("a", newline="") as f:
                    if text is None:
                        csv.writer(f).writerow(["" if row.get(c) is None else row.get(c) for c in self.COLUMNS])
                    else:
                        f.write(text)
            except OSError as exc:
                raise write_error(path, exc) from None
        self.rows += 1
        if self.tb is not None:
            for k, v in values.items():
                if k not in ("step", "epoch") and isinstance(v, (int, float)) and v is not None:
                    self.tb.add_scalar(f"{event}/{k}", v, values.get("step", 0))

    def image(self, tag: str, rgb: Any, step: int) -> None:
        """Log an (H, W, 3) uint8 RGB image to TensorBoard (when installed; rank 0)."""
        if self.tb is not None:
            self.tb.add_image(tag, rgb, step, dataformats="HWC")

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
