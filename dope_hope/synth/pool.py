"""The worker processes of :func:`dope_hope.synth.to_disk.generate_dataset`: each holds its own
:class:`~dope_hope.synth.generate.FrameGenerator` (and renderer) and writes the frames it is
given; the parent alone handles Ctrl-C and SIGTERM (it terminates the pool).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import signal
import threading
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dope_hope.synth.generate import FrameGenerator
from dope_hope.synth.writer import remove_stale_frame_temporaries

_WORKER: FrameGenerator | None = None


_WORKER_OUT: Path | None = None


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


class _CtrlCHeld:
    """Ctrl-C held back while worker processes start, and acted on once they have.

    The workers must never see SIGINT (the parent terminates them), including while their
    interpreter starts, before :func:`_init_worker` ignores it: a process started from a
    thread that blocks SIGINT inherits the block, and a Ctrl-C stays pending in it until the
    worker ignores the signal (which discards it). The parent's handler meanwhile only
    records a Ctrl-C (a KeyboardInterrupt inside ``Pool()`` would orphan half a pool);
    :meth:`release` restores the handler and raises the recorded interrupt, which the caller
    does inside the pool's ``with`` so that the started workers are terminated.
    """

    def __init__(self) -> None:
        self.active = _main_thread()
        self.caught = False
        self.previous: Any = None
        if self.active:
            self.previous = signal.getsignal(signal.SIGINT)
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            if self.previous is not signal.SIG_IGN:
                signal.signal(signal.SIGINT, self._record)

    def _record(self, signum: int, frame: Any) -> None:
        self.caught = True

    def release(self) -> None:
        """Restore Ctrl-C; one that came while held is acted on now (KeyboardInterrupt)."""
        if not self.active:
            return
        self.active = False
        signal.signal(signal.SIGINT, self.previous)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # a pending one is handled here
        if self.caught:
            if callable(self.previous):
                self.previous(signal.SIGINT, None)
            elif self.previous == signal.SIG_DFL:
                raise KeyboardInterrupt


def _init_worker(gen_kwargs: dict[str, Any], out_dir: str, threads: int) -> None:
    global _WORKER, _WORKER_OUT
    # The parent alone handles Ctrl-C and SIGTERM (it terminates the pool): a worker ignores
    # SIGINT (blocked since it started, see _CtrlCHeld; ignoring discards a pending one) and
    # dies quietly on SIGTERM.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # Share the cores between the workers' software rasterizers (Mesa llvmpipe) instead of
    # each one starting a thread per core (unless the user set these).
    os.environ.setdefault("LP_NUM_THREADS", str(threads))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER = FrameGenerator(**gen_kwargs)
    _WORKER_OUT = Path(out_dir)


def _work(index: int) -> int:
    assert _WORKER is not None and _WORKER_OUT is not None
    try:
        _WORKER.write_frame(_WORKER_OUT, index)
    except Exception as error:
        raise _picklable(error, index) from None
    return index


def _picklable(error: Exception, index: int) -> Exception:
    """``error`` if the pool can send it to the parent, else a RuntimeError with its text and
    traceback (an OpenGL error holds ctypes arguments, which do not pickle: the parent would
    see only "cannot pickle", not the error)."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:
        trace = "".join(traceback.format_exception(error)).rstrip()
        return RuntimeError(f"frame {index}: {type(error).__name__}: {error}\n{trace}")


def render_in_pool(gen_kwargs: dict[str, Any], out: Path, todo: list[int], workers: int,
                    done: Callable[[int], None]) -> None:
    """Write frames ``todo`` with ``workers`` spawned processes; ``done(i)`` once frame i is written."""
    ctx = mp.get_context("spawn")
    n_proc = min(workers, len(todo))
    threads = max(1, (os.cpu_count() or 1) // n_proc)
    # A Ctrl-C reaches the parent alone, which terminates the workers with the pool;
    # one that comes while they start is acted on once the pool stands (_CtrlCHeld).
    held = _CtrlCHeld()
    try:
        pool = ctx.Pool(n_proc, initializer=_init_worker, initargs=(gen_kwargs, str(out), threads))
    except BaseException:
        held.release()
        raise
    try:
        with pool:
            held.release()
            for i in pool.imap_unordered(_work, todo, chunksize=1):
                done(i)
    except BaseException:
        # Leaving the pool terminated and joined its workers: the temporary files of
        # the frames they were writing (Ctrl-C, SIGTERM, a failed frame) are nobody's now.
        remove_stale_frame_temporaries(out, set(todo))
        raise
