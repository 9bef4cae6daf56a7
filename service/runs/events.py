"""Progress events: published from worker threads, streamed to browsers as Server-Sent Events."""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

END = ("", "")  # the message that ends a stream


class EventBroker:
    def __init__(self, max_queue: int = 1000):
        self._lock = threading.Lock()
        self._subscribers: set[tuple[asyncio.AbstractEventLoop, asyncio.Queue]] = set()
        self.max_queue = max_queue
        self.closed = False

    def close(self) -> None:
        """Shutting down: every open stream gets END and ends (uvicorn waits for open connections
        before the app's shutdown runs, so streams must end first). Callable from any thread."""
        self.closed = True
        with self._lock:
            subscribers = list(self._subscribers)
        for loop, queue in subscribers:
            try:
                loop.call_soon_threadsafe(_offer, queue, END)
            except RuntimeError:  # loop closed
                pass

    def publish(self, event_type: str, data: dict[str, Any]) -> None:
        message = (event_type, json.dumps(data, default=str))
        with self._lock:
            subscribers = list(self._subscribers)
        for loop, queue in subscribers:
            try:
                loop.call_soon_threadsafe(_offer, queue, message)
            except RuntimeError:  # loop closed: the subscriber is gone
                self.unsubscribe((loop, queue))

    def subscribe(self) -> tuple[asyncio.AbstractEventLoop, asyncio.Queue]:
        token = (asyncio.get_running_loop(), asyncio.Queue(self.max_queue))
        with self._lock:
            self._subscribers.add(token)
        return token

    def unsubscribe(self, token) -> None:
        with self._lock:
            self._subscribers.discard(token)


def _offer(queue: asyncio.Queue, message) -> None:
    if queue.full():  # a slow browser loses old progress, never blocks the bench
        queue.get_nowait()
    queue.put_nowait(message)


def format_sse(event_type: str, data: str) -> str:
    return f"event: {event_type}\ndata: {data}\n\n"
