"""Per-step and per-epoch training metrics: ``metrics.csv`` and ``metrics.jsonl`` in the run folder."""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any


class MetricsLog:
    """Scalars to ``metrics.csv`` + ``metrics.jsonl`` (+ TensorBoard when installed); rank 0."""

    COLUMNS = ("event", "step", "epoch", "time_s", "lr", "loss", "images_per_s",
               "val_loss", "val_kp_acc", "val_kp_acc_decoded")

    def __init__(self, out: Path, enabled: bool):
        self.enabled = enabled
        self.out = out
        self.tb = None
        if not enabled:
            return
        self.csv_path = out / "metrics.csv"
        self.jsonl_path = out / "metrics.jsonl"
        if not self.csv_path.exists():
            with self.csv_path.open("w", newline="") as f:
                csv.writer(f).writerow(self.COLUMNS)
        try:
            from torch.utils.tensorboard import SummaryWriter
            self.tb = SummaryWriter(str(out / "tensorboard"))
        except ImportError:  # tensorboard is optional
            self.tb = None

    def write(self, event: str, **values: Any) -> None:
        if not self.enabled:
            return
        row = {"event": event, **values}
        with self.csv_path.open("a", newline="") as f:
            csv.writer(f).writerow(["" if row.get(c) is None else row.get(c) for c in self.COLUMNS])
        with self.jsonl_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        if self.tb is not None:
            for k, v in values.items():
                if k not in ("step", "epoch") and isinstance(v, (int, float)) and v is not None:
                    self.tb.add_scalar(f"{event}/{k}", v, values.get("step", 0))

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
