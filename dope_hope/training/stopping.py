"""Stopping a training run: Ctrl-C / SIGTERM finish the current step (a second one raises
KeyboardInterrupt), every rank agrees to stop when one wants to, and the trainer then writes
``last.pt`` and returns ``interrupted`` / ``terminated``.

:class:`StopControl` holds the run's stop request (``reason``); the trainer asks it after each
step whether every rank agrees to stop (:meth:`StopControl.agree`).
"""
from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any

import torch
import torch.distributed as dist

#: The reasons a run stops early, in the order the ranks agree on (the highest wins).
STOP_REASONS = (None, "time_limit", "terminated", "interrupted")


class StopControl:
    """A run's stop requests: signals, and the agreement of all ranks.

    Args:
        distributed: whether the run has several processes (they agree with an all-reduce).
        device: where the all-reduce's tensor lives ("cpu", or the process's CUDA device).
    """

    def __init__(self, distributed: bool, device: torch.device | str):
        self.distributed = distributed
        self.device = device
        self.reason: str | None = None
        self.signals_seen = 0

    def request(self, reason: str = "interrupted") -> None:
        """Stop after the current step (what Ctrl-C / SIGTERM do); the first reason stays."""
        self.reason = self.reason or reason

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.signals_seen += 1
        if self.signals_seen > 1:
            raise KeyboardInterrupt
        self.request("interrupted" if signum == signal.SIGINT else "terminated")

    def agree(self) -> bool:
        """True on every rank when any rank wants to stop (signal)."""
        if not self.distributed:
            return self.reason is not None
        t = torch.tensor([STOP_REASONS.index(self.reason)], dtype=torch.int32, device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        self.reason = STOP_REASONS[int(t.item())]
        return self.reason is not None

    @contextlib.contextmanager
    def signals(self) -> Iterator[None]:
        """Ctrl-C and SIGTERM request a stop while inside (the main thread only; elsewhere
        no signal handling); the previous handlers afterwards."""
        handlers = {}
        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, self._on_signal)
        except ValueError:  # not the main thread: no signal handling
            handlers = {}
        try:
            yield
        finally:
            for sig, h in handlers.items():
                signal.signal(sig, h)
