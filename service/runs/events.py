"""Progress events: published from worker threads, streamed to browsers as Server-Sent Events."""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

Message = tuple[str, str]  # (event type, its data as JSON)
Subscriber = tuple[asyncio.AbstractEventLoop, asyncio.Queue[Message]]  # a stream's loop and its queue

END: Message = ("", "")  # the message that ends a stream


class EventBroker:
    """Subscribers are a frozenset replaced whole on (un)subscribe, under a lock; publish and close read
    it with no lock, so close is safe from any context (a signal handler, the event loop, any thread)."""

    def __init__(self, max_queue: int = 1000):
        self._lock = threading.Lock()  # serialises subscribe and unsubscribe only
        self._subscribers: frozenset[Subscriber] = frozenset()
        self.max_queue = max_queue
        self.closed = False

    def close(self) -> None:
        """Shutting down: every open stream gets END and ends (uvicorn waits for open connections
        before the app's shutdown runs, so streams must end first). Takes no lock and waits on nothing;
        idempotent (a second call finds it closed)."""
        if self.closed:
            return
        self.closed = True
        for loop, queue in self._subscribers:
            try:
                loop.call_soon_threadsafe(_offer, queue, END)
            except RuntimeError:  # loop closed
                pass

    def publish(self, event_type: str, data: dict[str, Any]) -> None:
        message = (event_type, json.dumps(data, default=str))
        for loop, queue in self._subscribers:
            try:
                loop.call_soon_threadsafe(_offer, queue, message)
            except RuntimeError:  # loop closed: the subscriber is gone
                self.unsubscribe((loop, queue))

    def subscribe(self) -> Subscriber:
        token: Subscriber = (asyncio.get_running_loop(), asyncio.Queue(self.max_queue))
        with self._lock:
            self._subscribers = self._subscribers | {token}
        return token

    def unsubscribe(self, token: Subscriber) -> None:
        with self._lock:
            self._subscribers = self._subscribers - {token}


def _offer(queue: asyncio.Queue[Message], message: Message) -> None:
    if queue.full():  # a slow browser loses old progress, never blocks the bench
        queue.get_nowait()
    queue.put_nowait(message)


def format_sse(event_type: str, data: str) -> str:
    return f"event: {event_type}\ndata: {data}\n\n"
