"""The live node's pairing of images, camera infos and depth by stamp, newest frame first
(dope_hope/ros/frame_pairing.py), on a fake clock: no ROS needed."""
from __future__ import annotations

import threading

from dope_hope.ros.frame_pairing import LatestFramePairing

MS = 1_000_000


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def pairing(**kw) -> tuple[LatestFramePairing, Clock]:
    clock = Clock()
    return LatestFramePairing(clock=clock, **kw), clock


def test_an_image_takes_the_camera_info_of_its_own_stamp():
    p, _ = pairing(depth=False)
    p.add_info(1 * MS, b"info1")
    p.add_image(2 * MS, b"img2")
    assert p.take(timeout_s=0) is None  # its own info has not come
    p.add_info(2 * MS, b"info2")
    frame = p.take(timeout_s=0)
    assert (frame.stamp_ns, frame.image, frame.info, frame.depth) == (2 * MS, b"img2", b"info2", None)
    assert frame.arrival_s == 100.0


def test_depth_is_the_nearest_within_the_tolerance():
    p, _ = pairing(depth_tolerance_s=0.015)
    p.add_depth(90 * MS, b"d90")
    p.add_depth(104 * MS, b"d104")
    p.add_depth(110 * MS, b"d110")
    p.add_info(100 * MS, b"i")
    p.add_image(100 * MS, b"img")
    assert p.take(timeout_s=0).depth == b"d104"


def test_an_image_waits_for_its_depth_while_depth_flows_then_goes_without():
    p, clock = pairing(depth_tolerance_s=0.015, depth_wait_s=0.5)
    p.add_depth(0, b"d0")  # depth is flowing
    p.add_info(100 * MS, b"i")
    p.add_image(100 * MS, b"img")
    assert p.take(timeout_s=0) is None  # waits: its depth may still come
    clock.now += 0.6  # waited longer than depth_wait_s
    frame = p.take(timeout_s=0)
    assert frame.depth is None and p.counts.without_depth == 1


def test_an_image_goes_without_depth_once_the_depth_stream_has_passed_it():
    p, _ = pairing(depth_tolerance_s=0.015)
    p.add_depth(200 * MS, b"d200")
    p.add_info(100 * MS, b"i")
    p.add_image(100 * MS, b"img")
    assert p.take(timeout_s=0).depth is None


def test_without_any_depth_images_do_not_wait():
    p, _ = pairing()
    p.add_info(5 * MS, b"i")
    p.add_image(5 * MS, b"img")
    assert p.take(timeout_s=0).stamp_ns == 5 * MS


def test_the_latest_frame_wins_and_older_ones_are_dropped_and_counted():
    p, _ = pairing(depth=False)
    for s in (1, 2, 3):
        p.add_info(s * MS, b"i")
        p.add_image(s * MS, f"img{s}".encode())
    assert p.take(timeout_s=0).image == b"img3"
    assert (p.counts.images, p.counts.taken, p.counts.dropped) == (3, 1, 2)
    assert p.take(timeout_s=0) is None


def test_images_without_camera_info_leave_the_window_unpaired():
    p, _ = pairing(depth=False, keep=3)
    for s in range(5):
        p.add_image(s * MS, b"img")
    assert p.counts.unpaired == 2 and p.take(timeout_s=0) is None


def test_take_wakes_on_a_frame_from_another_thread_and_on_close():
    p = LatestFramePairing(depth=False)
    got = []
    worker = threading.Thread(target=lambda: got.append(p.take(timeout_s=5)))
    worker.start()
    p.add_image(7 * MS, b"img")
    p.add_info(7 * MS, b"i")
    worker.join(timeout=5)
    assert got[0].stamp_ns == 7 * MS
    closer = threading.Thread(target=lambda: got.append(p.take()))
    closer.start()
    p.close()
    closer.join(timeout=5)
    assert not closer.is_alive() and got[1] is None
