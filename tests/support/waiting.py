"""One way to wait in a test: poll a condition until it holds, with a timeout that only guards a hang."""

from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")
UNFINISHED = ("queued", "running", "paused")  # the states a job or a sweep leaves when its run ends


def wait_until(
    predicate: Callable[[], T], timeout_s: float = 120.0, what: str = "condition", poll_s: float = 0.05
) -> T:
    """The first truthy value of `predicate()`; TimeoutError naming `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise TimeoutError(f"{what} not reached within {timeout_s} s")


def wait_run_finished(
    read: Callable[[], dict], timeout_s: float = 120.0, what: str = "the run", poll_s: float = 0.1
) -> dict:
    """The first answer of `read()` (a job or a sweep, as the API or storage gives it) whose state is no
    longer queued, running or paused; TimeoutError naming `what` after `timeout_s`."""
    return wait_until(
        lambda: (body := read())["state"] not in UNFINISHED and body, timeout_s, f"{what} finished", poll_s
    )
