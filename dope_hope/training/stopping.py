"""Stopping a training run: Ctrl-C / SIGTERM finish the current step (a second one raises
KeyboardInterrupt), every rank agrees to stop when one wants to, and the trainer then writes
``last.pt`` and returns ``interrupted`` / ``terminated``.

:class:`StopControl` is a part of :class:`~dope_hope.training.trainer.Trainer`
(``stop_reason``, ``dist``, ``device``).
"""
from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any

import torch
import torch.distributed as dist


class StopControl:
    """The trainer's stop requests: signals, and the agreement of all ranks."""

    def request_stop(self, reason: str = "interrupted") -> None:
        """Stop after the current step (what Ctrl-C / SIGTERM do)."""
        self.stop_reason = self.stop_reason or reason

    def _on_signal(self, signum: int, frame: Any) -> None:
        self._signal_count += 1
        if self._signal_count > 1:
            raise KeyboardInterrupt
        self.request_stop("interrupted" if signum == signal.SIGINT else "terminated")

    def _agree_stop(self) -> bool:
        """True on every rank when any rank wants to stop (signal)."""
        if not self.dist.active:
            return self.stop_reason is not None
        reasons = (None, "time_limit", "terminated", "interrupted")
        t = torch.tensor([reasons.index(self.stop_reason)], dtype=torch.int32, device=self.device if self.cuda else "cpu")
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        self.stop_reason = reasons[int(t.item())]
        return self.stop_reason is not None

    @contextlib.contextmanager
    def stop_signals(self) -> Iterator[None]:
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
