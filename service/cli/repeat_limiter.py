"""A log that does not flood: the same warning or error more than `max_per_window` times within
`window_s` is summarised in one line ("... repeated 14,322 times in the last 10 s") instead of written
each time. Without it, a process out of file descriptors wrote 65 MB of "Too many open files" in 30 s.

Installed as a filter on the handlers of the loggers `serve` writes through (the root logger's, which
asyncio's records reach, and uvicorn's own), so it sees records of child loggers too. INFO and below
(uvicorn's access lines) pass untouched: one line per request is the record of what was asked.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

MAX_KEYS = 256  # distinct messages tracked at once; beyond it they share one key per logger and level


@dataclass
class _Window:
    started: float
    first: logging.LogRecord
    count: int = 1  # records of this key in the window, the ones written included
    timer: threading.Timer | None = field(default=None, repr=False)


class RepeatLimiter(logging.Filter):
    """One per handler: the summaries are written through the handler whose records were held back."""

    def __init__(
        self,
        handler: logging.Handler,
        max_per_window: int = 5,
        window_s: float = 10.0,
        clock=time.monotonic,
        timers: bool = True,
    ):
        super().__init__()
        self.handler = handler
        self.max_per_window = max_per_window
        self.window_s = window_s
        self.clock = clock
        self.timers = timers  # False: summaries only when flush() is called (tests with their own clock)
        self._lock = threading.Lock()
        self._windows: dict[tuple, _Window] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING or getattr(record, "repeat_summary", False):
            return True
        now = self.clock()
        key = _key(record)
        with self._lock:
            expired = self._take_expired(now)
            if key not in self._windows and len(self._windows) >= MAX_KEYS:
                key = (record.name, record.levelno, "<other messages>")
            window = self._windows.get(key)
            if window is None:
                self._windows[key] = _Window(started=now, first=record)
                passes = True
            else:
                window.count += 1
                passes = window.count <= self.max_per_window
                if not passes and window.timer is None and self.timers:
                    # the summary is due at the window's end even if nothing more is logged
                    window.timer = threading.Timer(max(0.0, window.started + self.window_s - now) + 0.05, self.flush)
                    window.timer.daemon = True
                    window.timer.start()
        self._write(expired)  # outside the lock: handle() calls this filter again
        return passes

    def flush(self) -> None:
        """Write the summaries of every window that has ended."""
        with self._lock:
            expired = self._take_expired(self.clock())
        self._write(expired)

    def close(self) -> None:
        """The summaries still held, written now (the end of the process), the timers stopped."""
        with self._lock:
            expired = self._take_expired(float("inf"))
        self._write(expired)

    def _take_expired(self, now: float) -> list[_Window]:
        ended = [k for k, w in self._windows.items() if now - w.started >= self.window_s]
        taken = []
        for k in ended:
            w = self._windows.pop(k)
            if w.timer is not None:
                w.timer.cancel()
            if w.count > self.max_per_window:
                taken.append(w)
        return taken

    def _write(self, expired: list[_Window]) -> None:
        for window in expired:
            self.handler.handle(_summary(window, self.window_s, self.max_per_window))


def _key(record: logging.LogRecord) -> tuple:
    # the message template, not its arguments: "connection from %s refused" is one message for any client
    return (record.name, record.levelno, str(record.msg)[:500], record.exc_info[0] if record.exc_info else None)


def _summary(window: _Window, window_s: float, written: int) -> logging.LogRecord:
    first = window.first
    message = first.getMessage()
    text = message.splitlines()[0] if message else ""
    if first.exc_info and first.exc_info[1] is not None:
        text += f" ({type(first.exc_info[1]).__name__}: {first.exc_info[1]})"
    record = logging.LogRecord(
        first.name,
        first.levelno,
        first.pathname,
        first.lineno,
        "%s ... repeated %s times in the last %g s (%s of them not written)",
        (text, f"{window.count:,}", window_s, f"{window.count - written:,}"),
        None,
    )
    record.repeat_summary = True
    return record


def install(loggers: tuple[str, ...] = ("", "uvicorn", "uvicorn.access"), **limits) -> list[RepeatLimiter]:
    """A RepeatLimiter on every handler of `loggers` (each handler once): call it after uvicorn's
    logging configuration (uvicorn.Config configures its loggers when it is made)."""
    installed: list[RepeatLimiter] = []
    seen: set[int] = set()
    for name in loggers:
        for handler in logging.getLogger(name).handlers:
            if id(handler) in seen:
                continue
            seen.add(id(handler))
            limiter = RepeatLimiter(handler, **limits)
            handler.addFilter(limiter)
            installed.append(limiter)
    return installed
