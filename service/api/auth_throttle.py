"""Failed authentications throttled per client address: a client that sent `max_failures` unknown or
revoked tokens within `window_s` is answered 429 (with Retry-After) on every route that needs a token,
whatever token it sends, until the oldest of those failures is `window_s` old. Guessing a token is then
`max_failures` tries per window per address; other clients are not affected.

A success does not clear a client's failures: with a valid viewer token an attacker could otherwise
reset its count between guesses at an operator route. A missing token is not a failure (a dashboard
that has none yet is not guessing)."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque

log = logging.getLogger(__name__)

MAX_CLIENTS = 10_000  # addresses tracked at once; the one that failed longest ago is forgotten first


class AuthThrottle:
    def __init__(self, max_failures: int, window_s: float, clock=time.monotonic):
        self.max_failures = max_failures
        self.window_s = window_s
        self.clock = clock
        self._lock = threading.Lock()  # sync dependencies run on the thread pool
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()

    def retry_after_s(self, client: str) -> int | None:
        """Whole seconds until `client` may try a token again; None: it may now."""
        now = self.clock()
        with self._lock:
            failures = self._recent(client, now)
            if failures is None or len(failures) < self.max_failures:
                return None
            return max(1, math.ceil(failures[0] + self.window_s - now))

    def failed(self, client: str) -> None:
        """`client` sent a token that is unknown or revoked."""
        now = self.clock()
        with self._lock:
            failures = self._recent(client, now)
            if failures is None:
                failures = self._failures[client] = deque(maxlen=self.max_failures)
                while len(self._failures) > MAX_CLIENTS:
                    self._failures.popitem(last=False)
            failures.append(now)
            self._failures.move_to_end(client)
            throttled_s = failures[0] + self.window_s - now if len(failures) == self.max_failures else None
        if throttled_s is not None:
            log.warning(
                "client %s sent %d unknown or revoked tokens within %g s: it is answered 429 for the next %d s "
                "(server.auth_max_failures, server.auth_failure_window_s)",
                client,
                self.max_failures,
                self.window_s,
                max(1, math.ceil(throttled_s)),
            )

    def _recent(self, client: str, now: float) -> deque[float] | None:
        failures = self._failures.get(client)
        if failures is None:
            return None
        while failures and failures[0] <= now - self.window_s:
            failures.popleft()
        if not failures:
            del self._failures[client]
            return None
        return failures
