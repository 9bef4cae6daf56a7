"""The one way a command waits: for a job or a sweep it submitted, in this process's service.

The service's EventBroker is subscribed before the submission (no early event is missed); the
state is read from storage after every event the caller's `on_event` marks as its own, and at least
every `interval_s`, so a lost event never hangs the wait. Bounded by `timeout_s`.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any, Callable, TypeVar

T = TypeVar("T")
K = TypeVar("K")


def follow(
    service,
    submit: Callable[[], K],
    read: Callable[[K], T | None],
    *,
    timeout_s: float,
    timeout_message: Callable[[K], str],
    interval_s: float,
    on_event: Callable[[K, str, dict[str, Any]], bool] | None = None,
) -> T:
    """Submit, then wait until `read(key)` returns what was waited for (not None); `on_event(key, kind,
    event)` sees every event published meanwhile and returns True when the state is to be read now.
    TimeoutError(timeout_message(key)) after `timeout_s`."""

    async def wait() -> T:
        token = service.broker.subscribe()  # before submitting: no early event is missed
        queue = token[1]
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        try:
            key = submit()
            while True:
                value = read(key)
                if value is not None:
                    return value
                next_read = loop.time() + interval_s
                while True:
                    remaining = deadline - loop.time()
                    if remaining <= 0:
                        raise TimeoutError(timeout_message(key))
                    try:
                        kind, data = await asyncio.wait_for(
                            queue.get(), timeout=min(next_read - loop.time(), remaining)
                        )
                    except TimeoutError:
                        break
                    if on_event is not None and on_event(key, kind, json.loads(data)):
                        break
        finally:
            service.broker.unsubscribe(token)

    return asyncio.run(wait())
