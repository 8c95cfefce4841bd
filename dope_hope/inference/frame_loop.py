"""A frame loop that does not fall behind its source: frames it cannot process are dropped.

:func:`run_stream` reads a :class:`~dope_hope.io.streams.FrameSource` in a background thread
(:class:`FrameFeed`) and hands frames to a callback (the predictors and the outputs):

* ``latest=True`` (a live camera; a video file with ``--realtime``): one slot holding the
  newest frame. A frame replaced before the loop took it is **dropped and counted**, never
  queued, so the loop always works on the newest frame and its latency stays one frame's
  processing time however slow the processing is.
* ``latest=False`` (a video file): every frame is processed; the reader decodes up
  to :data:`PREFETCH` frames ahead while the loop works, then waits for it.
* ``pace=True`` plays a file as if it were live: each frame is published at its timestamp
  (the file's frame rate), and with ``latest=True`` the loop drops what it cannot keep up with.
  A jump between two frames' timestamps of more than :data:`MAX_PACE_GAP_S` either way (a
  recording whose stamps switch from simulated to wall-clock time) is not waited for: the
  clock restarts at that frame, and a warning says so.

Frames/s "end to end" = processed frames / seconds from taking the first frame to the end of
the last callback: decoding (where not overlapped), network, decode + PnP, -LS / ICP and the
outputs, all included. Ctrl-C ends the stream like its end (what was processed is kept).
"""
from __future__ import annotations

import collections
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from dope_hope.io.streams import Frame, FrameSource, Grabbed

#: Frames the reader decodes ahead of the loop when every frame is processed.
PREFETCH = 2
#: Largest jump between two frames' timestamps that pacing waits for, seconds.
MAX_PACE_GAP_S = 10.0
#: Seconds to wait for the reader thread to stop at the end.
JOIN_TIMEOUT_S = 5.0


def passive_openmp() -> bool:
    """Make OpenMP's idle threads (PyTorch's CPU pool) sleep instead of spin
    (``OMP_WAIT_POLICY=PASSIVE``) unless the variable is set already. In a frame loop the
    network runs between the single-threaded decode / PnP / -LS and the reader thread's video
    decoding; spinning threads take those cores (bench/RESULTS.md "Video stream"). OpenMP reads
    the variable when torch is first imported, so this acts only before that; True when it did.
    """
    if "torch" in sys.modules or "OMP_WAIT_POLICY" in os.environ:
        return False
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True


@dataclass
class StreamStats:
    """What a stream run did. read: frames taken from the source; processed: frames the
    callback got; dropped: frames replaced before the loop took them; seconds: from taking the
    first frame to the end of the last callback; stopped: why it ended ("end of stream",
    "interrupted", "max frames", "stopped by the callback", "ended early: ..." or a source
    error's message); expected: the frame count the file states when its stream ended before
    it (a corrupt or truncated file), else None."""

    read: int = 0
    processed: int = 0
    dropped: int = 0
    seconds: float = 0.0
    stopped: str = "end of stream"
    expected: int | None = None

    @property
    def fps(self) -> float:
        """Processed frames per second, end to end (0 when nothing ran)."""
        return self.processed / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        return (f"{self.read} frame(s) read, {self.processed} processed, {self.dropped} dropped; "
                f"{self.fps:.1f} frames/s end to end ({self.stopped})")


class FrameFeed:
    """Iterate the :class:`Grabbed` items of ``source``, read in a daemon thread (module
    docstring for ``latest`` and ``pace``); stops after ``max_frames`` read when given.
    An exception in the reader is raised by the iteration once the frames before it are out.
    """

    def __init__(self, source: FrameSource, latest: bool, pace: bool = False, max_frames: int | None = None,
                 warn: Callable[[str], None] | None = None):
        self.source, self.latest, self.pace, self.max_frames = source, latest, pace, max_frames
        self.warn = warn
        self.read = 0
        self.dropped = 0
        self.error: BaseException | None = None
        self.reached_max = False
        self._items: collections.deque[Grabbed] = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._thread = threading.Thread(target=self._run, name=f"dope-hope-reader-{source.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            start = previous = None  # monotonic time of timestamp 0 when pacing; the last timestamp
            for item in self.source.grab():
                if self._stop.is_set():
                    break
                if self.pace and item.timestamp_s is not None:
                    gap = None if previous is None else item.timestamp_s - previous
                    if gap is not None and abs(gap) > MAX_PACE_GAP_S:
                        start = None
                        if self.warn is not None:
                            self.warn(f"{self.source.name}: frame {item.index} is stamped {gap:+.3f} s from the one "
                                      f"before (more than {MAX_PACE_GAP_S:g} s either way): --realtime plays it "
                                      "at once and paces from there")
                    previous = item.timestamp_s
                    start = time.monotonic() - item.timestamp_s if start is None else start
                    wait = start + item.timestamp_s - time.monotonic()
                    if wait > 0 and self._stop.wait(wait):
                        break
                with self._cond:
                    if self.latest:
                        if self._items:
                            self._items.clear()
                            self.dropped += 1
                    else:
                        while len(self._items) >= PREFETCH and not self._stop.is_set():
                            self._cond.wait()
                    self._items.append(item)
                    self.read += 1
                    self._cond.notify_all()
                if self.max_frames is not None and self.read >= self.max_frames:
                    self.reached_max = True
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the consuming thread
            self.error = exc
        finally:
            try:
                self.source.close()
            finally:
                with self._cond:
                    self._done = True
                    self._cond.notify_all()

    def __iter__(self):
        while True:
            with self._cond:
                while not self._items and not self._done:
                    self._cond.wait(0.1)  # a timeout keeps Ctrl-C responsive
                if self._items:
                    item = self._items.popleft()
                    self._cond.notify_all()
                elif self.error is not None:
                    raise self.error
                else:
                    return
            yield item

    def close(self) -> None:
        """Stop the reader (it releases the source) and wait for it a few seconds."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(JOIN_TIMEOUT_S)


def run_stream(source: FrameSource, process: Callable[[Frame], bool | None], latest: bool | None = None,
               pace: bool = False, max_frames: int | None = None,
               on_source_error: Callable[[BaseException], bool] | None = None,
               warn: Callable[[str], None] | None = None) -> StreamStats:
    """Feed the frames of ``source`` to ``process`` (module docstring); returns the stats.

    ``latest`` defaults to ``source.live or pace``. ``process(frame)`` returning False ends
    the stream. A source error (e.g. a camera unplugged) is raised unless
    ``on_source_error(exc)`` returns True, which ends the stream as if it had ended there.
    A file whose frames end before the count it states ends with ``stats.expected`` set.
    Ctrl-C ends the stream like its end. The source is closed on return. ``warn``: told of a
    timestamp jump that pacing does not wait for.
    """
    latest = (source.live or pace) if latest is None else latest
    feed = FrameFeed(source, latest=latest, pace=pace, max_frames=max_frames, warn=warn)
    stats = StreamStats()
    t_first = t_last = None
    try:
        for item in feed:
            t_first = time.perf_counter() if t_first is None else t_first
            frame = item.load()
            keep_going = process(frame)
            stats.processed += 1
            t_last = time.perf_counter()
            if keep_going is False:
                stats.stopped = "stopped by the callback"
                break
        else:
            if feed.reached_max:
                stats.stopped = "max frames"
            elif not source.live and source.length is not None and feed.read < source.length:
                stats.expected = source.length
                stats.stopped = f"ended early: {feed.read} of the {source.length} frames the file states"
    except KeyboardInterrupt:
        stats.stopped = "interrupted"
    except Exception as exc:
        if exc is not feed.error or on_source_error is None or not on_source_error(exc):
            raise
        stats.stopped = str(exc)
    finally:
        feed.close()
        stats.read, stats.dropped = feed.read, feed.dropped
        if t_first is not None and t_last is not None:
            stats.seconds = t_last - t_first
    return stats
