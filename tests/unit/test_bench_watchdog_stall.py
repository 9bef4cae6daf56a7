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
