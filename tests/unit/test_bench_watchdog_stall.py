"""The bench watchdog's stall names where the run's worker is stuck (service/bench/watchdog.py)."""

from __future__ import annotations

import threading
import time

from service.bench.watchdog import BenchWatchdog


def worker_stuck_in_storage(watchdog: BenchWatchdog, release: threading.Event) -> None:
    watchdog.arm()
    release.wait(10.0)  # silent: no kick while "the database" hangs


def test_a_stall_names_the_worker_s_function_and_line():
    watchdog = BenchWatchdog(lambda: None, lambda: None, bound_s=0.2)
    release = threading.Event()
    worker = threading.Thread(target=worker_stuck_in_storage, args=(watchdog, release))
    watchdog.start()
    try:
        worker.start()
        deadline = time.monotonic() + 10.0
        while watchdog.tripped is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert watchdog.tripped is not None, "no stall seen"
        reason = watchdog.tripped.reason
        # the innermost frame is threading's wait; the reason names the project's own innermost frame
        assert "did not report" in reason and "stuck at test_bench_watchdog_stall.py:" in reason, reason
        assert "in worker_stuck_in_storage" in reason, reason
    finally:
        release.set()
        worker.join(5.0)
        watchdog.close()


def wait_for_trip(watchdog: BenchWatchdog, within_s: float) -> None:
    deadline = time.monotonic() + within_s
    while watchdog.tripped is None and time.monotonic() < deadline:
        time.sleep(0.02)


def test_answers_on_the_run_s_own_thread_keep_it_alive_answers_elsewhere_do_not():
    """bus_answered: an SDO transfer answered on the armed run's thread is its loop at work (a move of many
    transfers on a slow bus); the status poll's answers on another thread say nothing of the run."""
    watchdog = BenchWatchdog(lambda: None, lambda: None, bound_s=0.3)
    watchdog.start()
    try:
        watchdog.arm()  # this thread is the run's worker
        for _ in range(40):  # 1.2 s of transfers, 4 x the bound, no guard check between them
            time.sleep(0.03)
            watchdog.bus_answered()
        assert watchdog.tripped is None, watchdog.tripped
        poll = threading.Thread(target=lambda: [(watchdog.bus_answered(), time.sleep(0.03)) for _ in range(60)])
        poll.start()  # the worker falls silent while another thread's transfers are answered
        wait_for_trip(watchdog, 10.0)
        poll.join(5.0)
        assert watchdog.tripped is not None and "did not report" in watchdog.tripped.reason
    finally:
        watchdog.disarm()
        watchdog.close()
