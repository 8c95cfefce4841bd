"""A live camera's messages paired into frames, the newest frame first: the inputs of the ROS 2
node (:mod:`dope_hope.ros.node`), kept still serialized so that the subscription callbacks
stay cheap.

* **Camera info**: each image takes the CameraInfo of its own header stamp, as
  image_transport's camera subscriber does (an exact stamp match); a change of size or K thus
  holds from the frame it comes with.
* **Depth** (optional): the depth message whose stamp is nearest to the image's, within a
  tolerance. An image waits for its depth only while depth is flowing: without a depth
  message in the last ``depth_wait_s``, once the depth stream has passed the image's stamp,
  or after waiting ``depth_wait_s`` itself, it goes without depth (counted).
* **Latest frame wins**: the worker takes the newest complete frame; every older image still
  waiting is dropped then (counted), never queued. An image whose camera info never comes
  leaves the window of :attr:`LatestFramePairing.keep` images unpaired (counted).

Hand-written: message_filters' ApproximateTime / ExactTime synchronizers are not among the
pip wheels, and neither drops for the newest frame.
"""
from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class CameraFrame:
    """One image with the camera info of its stamp and its depth (or None), all serialized.

    stamp_ns: the image header's stamp; arrival_s: the clock's time (s) when the image arrived.
    """

    stamp_ns: int
    image: bytes
    info: bytes
    depth: bytes | None
    arrival_s: float


@dataclass
class PairingCounts:
    """images: received; taken: handed to the worker; dropped: replaced by a newer frame before
    the worker took them; unpaired: left the window without their camera info; without_depth:
    taken with depth on but no depth within the tolerance."""

    images: int = 0
    taken: int = 0
    dropped: int = 0
    unpaired: int = 0
    without_depth: int = 0


class LatestFramePairing:
    """Thread-safe pairing (module docstring): ``add_*`` from the subscriptions, :meth:`take`
    from the worker.

    Args:
        depth: pair depth at all (False: every frame without depth, nothing waits for it).
        depth_tolerance_s: the largest image-to-depth stamp difference, s.
        depth_wait_s: how long an image waits for its depth while depth flows, s.
        keep: images (and camera infos, depth images) held at most.
        clock: seconds, monotonic (arrival times and waits).
    """

    def __init__(self, depth: bool = True, depth_tolerance_s: float = 0.015, depth_wait_s: float = 0.5,
                 keep: int = 16, clock: Callable[[], float] = time.perf_counter):
        self.depth, self.depth_tolerance_ns, self.depth_wait_s = depth, round(depth_tolerance_s * 1e9), depth_wait_s
        self.keep, self.clock = keep, clock
        self.counts = PairingCounts()
        self._cond = threading.Condition()
        self._images: collections.OrderedDict[int, tuple[bytes, float]] = collections.OrderedDict()
        self._infos: collections.OrderedDict[int, bytes] = collections.OrderedDict()
        self._depths: collections.OrderedDict[int, bytes] = collections.OrderedDict()
        self._last_depth_s: float | None = None
        self._closed = False

    # ------------------------------------------------------------------ inputs
    def add_image(self, stamp_ns: int, data: bytes) -> None:
        with self._cond:
            self.counts.images += 1
            self._images.pop(stamp_ns, None)
            self._images[stamp_ns] = (data, self.clock())
            while len(self._images) > self.keep:
                self._images.popitem(last=False)
                self.counts.unpaired += 1
            self._cond.notify_all()

    def add_info(self, stamp_ns: int, data: bytes) -> None:
        with self._cond:
            self._bounded_put(self._infos, stamp_ns, data)
            self._cond.notify_all()

    def add_depth(self, stamp_ns: int, data: bytes) -> None:
        if not self.depth:
            return
        with self._cond:
            self._bounded_put(self._depths, stamp_ns, data)
            self._last_depth_s = self.clock()
            self._cond.notify_all()

    def _bounded_put(self, store: collections.OrderedDict, stamp_ns: int, data: bytes) -> None:
        store.pop(stamp_ns, None)
        store[stamp_ns] = data
        while len(store) > self.keep:
            store.popitem(last=False)

    def close(self) -> None:
        """Wake :meth:`take` for good (it returns None)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # ------------------------------------------------------------------ output
    def _depth_for(self, stamp_ns: int, arrival_s: float, now: float) -> tuple[bool, bytes | None]:
        """(ready, depth or None) of an image whose camera info is there."""
        if not self.depth:
            return True, None
        near = [s for s in self._depths if abs(s - stamp_ns) <= self.depth_tolerance_ns]
        if near:
            return True, self._depths[min(near, key=lambda s: abs(s - stamp_ns))]
        flowing = self._last_depth_s is not None and now - self._last_depth_s <= self.depth_wait_s
        passed = bool(self._depths) and max(self._depths) > stamp_ns + self.depth_tolerance_ns
        return (not flowing or passed or now - arrival_s > self.depth_wait_s), None

    def _newest_ready(self) -> CameraFrame | None:
        now = self.clock()
        for stamp in sorted(self._images, reverse=True):
            if stamp not in self._infos:
                continue
            data, arrival = self._images[stamp]
            ready, depth = self._depth_for(stamp, arrival, now)
            if ready:
                return CameraFrame(stamp, data, self._infos[stamp], depth, arrival)
        return None

    def take(self, timeout_s: float | None = None) -> CameraFrame | None:
        """The newest complete frame (older waiting images dropped and counted), waiting up to
        ``timeout_s`` (None: until one comes); None on timeout or after :meth:`close`."""
        deadline = None if timeout_s is None else self.clock() + timeout_s
        with self._cond:
            while not self._closed:
                frame = self._newest_ready()
                if frame is not None:
                    older = [s for s in self._images if s < frame.stamp_ns]
                    for s in older:
                        del self._images[s]
                    self.counts.dropped += len(older)
                    del self._images[frame.stamp_ns]
                    self.counts.taken += 1
                    self.counts.without_depth += int(self.depth and frame.depth is None)
                    return frame
                left = None if deadline is None else deadline - self.clock()
                if left is not None and left <= 0:
                    return None
                # an image waiting for its depth becomes ready with time alone: look again soon
                step = self.depth_wait_s / 4 if self._images else None
                waits = [x for x in (left, step) if x is not None]
                self._cond.wait(min(waits) if waits else None)
            return None
