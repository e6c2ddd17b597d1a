"""The stage worker's inbox: bounded rings filled by Zenoh callbacks, and one event to sleep on.

The rings and the event are plain Python, so these run without a Zenoh session; the end-to-end
behaviour (a slow stage works on the newest scan, a stage stops on a signal) is in
tests/integration/test_runtime.py.
"""

from __future__ import annotations

import threading
import time

from services.shell.stage import Inbox


def test_a_ring_keeps_the_newest_samples_in_order():
    ring = Inbox().ring(2)
    for sample in ("a", "b", "c"):
        ring(sample)
    assert list(iter(ring.try_recv, None)) == ["b", "c"]
    assert ring.try_recv() is None


def test_wait_returns_at_once_for_a_sample_that_came_before_it_and_times_out_without_one():
    inbox = Inbox()
    ring = inbox.ring(4)
    ring("a")
    started = time.monotonic()
    inbox.wait(5.0)
    assert time.monotonic() - started < 1.0
    assert ring.try_recv() == "a"
    started = time.monotonic()
    inbox.wait(0.05)
    assert time.monotonic() - started >= 0.04


def test_a_sample_from_another_thread_wakes_a_waiting_worker():
    inbox = Inbox()
    ring = inbox.ring(4)
    timer = threading.Timer(0.05, ring, args=("late",))
    timer.start()
    started = time.monotonic()
    inbox.wait(5.0)
    timer.join()
    assert time.monotonic() - started < 1.0
    assert ring.try_recv() == "late"


def test_a_sample_landing_between_the_wake_and_the_drain_is_not_lost():
    inbox = Inbox()
    rings = [inbox.ring(4), inbox.ring(4)]
    rings[0]("first")
    inbox.wait(5.0)  # woken; the event is cleared before the worker drains
    rings[1]("second")  # lands after the clear
    assert [ring.try_recv() for ring in rings] == ["first", "second"]
    rings[0]("third")  # and the next wait is woken by what comes after the drain
    started = time.monotonic()
    inbox.wait(5.0)
    assert time.monotonic() - started < 1.0
