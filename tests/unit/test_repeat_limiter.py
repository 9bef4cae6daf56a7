"""The log that does not flood (service/cli/repeat_limiter.py): a warning or error repeated more than
`max_per_window` times in a window is written that many times, then summarised in one line."""

from __future__ import annotations

import logging

import pytest

from service.cli.repeat_limiter import RepeatLimiter, install
from tests.support.waiting import wait_until


class _Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class _Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@pytest.fixture
def logger(request):
    log = logging.getLogger(f"test.repeat.{request.node.name}")
    log.propagate = False
    log.setLevel(logging.INFO)
    kept = _Kept()
    log.addHandler(kept)
    yield log, kept
    log.removeHandler(kept)


def test_a_flood_is_written_five_times_then_summarised_with_its_count(logger):
    log, kept = logger
    clock = _Clock()
    limiter = RepeatLimiter(kept, max_per_window=5, window_s=10, clock=clock, timers=False)
    kept.addFilter(limiter)
    for _ in range(14_322):
        log.error("socket.accept() out of system resource: %s", "[Errno 24] Too many open files")
    assert len(kept.lines) == 5
    clock.now += 10
    limiter.flush()
    assert len(kept.lines) == 6
    assert kept.lines[-1] == (
        "socket.accept() out of system resource: [Errno 24] Too many open files ... repeated 14,322 times "
        "in the last 10 s (14,317 of them not written)"
    )
    # a new window: the message is written again, up to five times
    log.error("socket.accept() out of system resource: %s", "[Errno 24] Too many open files")
    assert len(kept.lines) == 7


def test_other_messages_and_info_lines_are_not_held_back(logger):
    log, kept = logger
    clock = _Clock()
    kept.addFilter(RepeatLimiter(kept, max_per_window=2, window_s=10, clock=clock, timers=False))
    for i in range(10):
        log.warning("connection from %s closed", f"client {i}")  # one message: its arguments vary
        log.info('%s - "GET / HTTP/1.1" 200', f"client {i}")  # access lines: one per request, always
    log.error("another message")
    assert sum("closed" in line for line in kept.lines) == 2
    assert sum("GET /" in line for line in kept.lines) == 10
    assert kept.lines[-1] == "another message"


def test_a_window_that_ends_in_silence_is_summarised_by_its_timer(logger):
    log, kept = logger
    kept.addFilter(RepeatLimiter(kept, max_per_window=1, window_s=0.2))
    for _ in range(3):
        log.warning("the same")
    assert kept.lines == ["the same"]
    # nothing more is logged: the summary comes at the end of the window all the same
    wait_until(lambda: len(kept.lines) == 2, 10, "the summary")
    assert kept.lines[1] == "the same ... repeated 3 times in the last 0.2 s (2 of them not written)"


def test_close_writes_what_is_still_held(logger):
    log, kept = logger
    clock = _Clock()
    limiter = RepeatLimiter(kept, max_per_window=1, window_s=10, clock=clock, timers=False)
    kept.addFilter(limiter)
    log.error("boom")
    log.error("boom")
    limiter.close()
    assert kept.lines == ["boom", "boom ... repeated 2 times in the last 10 s (1 of them not written)"]


def test_install_puts_one_limiter_on_each_handler_of_the_loggers(logger):
    log, kept = logger
    limiters = install(loggers=(log.name, log.name), max_per_window=1, window_s=10)
    try:
        # the logger named twice, its handler limited once (pytest may add handlers of its own)
        assert [limiter.handler for limiter in limiters].count(kept) == 1
        log.error("x")
        log.error("x")
        assert kept.lines == ["x"]
    finally:
        for limiter in limiters:
            limiter.handler.removeFilter(limiter)
