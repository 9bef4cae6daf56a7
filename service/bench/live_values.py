"""The latest reading of each bench value with the time it was taken, for the live bench status.

Written from several threads (the status poller's SDO/SCPI reads, a run's session through a
publisher it is handed, the bench's own commands), read by `Bench.status()`: each value carries its
age, so a value nobody refreshed reads as stale instead of as current.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

STALE_AFTER_S = 3.0  # a value older than this is marked stale (the poller refreshes at 1 Hz)


class LiveValues:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, dict[str, tuple[Any, float]]] = {}  # group -> field -> (value, monotonic)

    def publish(self, group: str, **values: Any) -> None:
        now = time.monotonic()
        with self._lock:
            fields = self._values.setdefault(group, {})
            for key, value in values.items():
                fields[key] = (value, now)

    def publisher(self, group: str) -> Callable[..., None]:
        """A callable for a collaborator that must not know the bench (the measurement session)."""
        return lambda **values: self.publish(group, **values)

    def group(self, group: str) -> tuple[dict[str, Any], dict[str, float]]:
        """(values, ages in s) of one group."""
        now = time.monotonic()
        with self._lock:
            fields = dict(self._values.get(group, {}))
        return ({k: v for k, (v, _) in fields.items()}, {k: round(now - t, 2) for k, (_, t) in fields.items()})
