"""The master side of a real pty, written from a thread: a DAQ for the reader to open by its /dev/pts path."""

from __future__ import annotations

import os
import select
import threading
import time
import tty


class PtyWriter:
    """The pty master side: writes byte pieces from a thread (blocking writes, like the emulator)."""

    def __init__(self):
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self.path = os.ttyname(self.slave_fd)
        self.bytes_written = 0
        self.error: BaseException | None = None
        self.piece_times: list[float] = []  # write_at_rate: time.monotonic() after each piece went in
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()  # close(): a writer blocked on a full pty gives up at once

    def write(self, data: bytes) -> None:
        """All of data, from the calling thread (blocks while the pty is full)."""
        view = memoryview(data)
        while view:
            if self._stop.is_set():
                raise OSError("pty writer closed")
            if not select.select([], [self.master_fd], [], 0.05)[1]:
                continue  # full: the reader has not taken it yet
            written = os.write(self.master_fd, view)
            self.bytes_written += written
            view = view[written:]

    def write_in_thread(self, data: bytes, piece_bytes: int = 4096) -> threading.Thread:
        def run():
            try:
                for start in range(0, len(data), piece_bytes):
                    self.write(data[start : start + piece_bytes])
            except OSError as exc:
                self.error = exc

        self._thread = threading.Thread(target=run, name="pty-writer", daemon=True)
        self._thread.start()
        return self._thread

    def write_at_rate(self, data: bytes, piece_bytes: int, bytes_per_s: float) -> threading.Thread:
        """Pieces of data at a steady rate on the wall clock, as a DAQ streams (piece k is due at
        k * piece_bytes / bytes_per_s), from a thread; piece_times[k] is when piece k went in."""
        self.piece_times = []

        def run():
            t0 = time.monotonic()
            try:
                for k, start in enumerate(range(0, len(data), piece_bytes)):
                    delay = t0 + start / bytes_per_s - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    self.write(data[start : start + piece_bytes])
                    self.piece_times.append(time.monotonic())
            except OSError as exc:
                self.error = exc

        self._thread = threading.Thread(target=run, name="pty-writer-paced", daemon=True)
        self._thread.start()
        return self._thread

    def close_master(self) -> None:
        if self.master_fd >= 0:
            os.close(self.master_fd)
            self.master_fd = -1

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.close_master()
        if self.slave_fd >= 0:
            os.close(self.slave_fd)
            self.slave_fd = -1
