"""One way to wait in a test: poll a condition until it holds, with a timeout that only guards a hang."""
from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")


def wait_until(predicate: Callable[[], T], timeout_s: float = 120.0, what: str = "condition",
               poll_s: float = 0.05) -> T:
    """The first truthy value of `predicate()`; TimeoutError naming `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise TimeoutError(f"{what} not reached within {timeout_s} s")
