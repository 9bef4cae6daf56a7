"""The master side of a real pty, written from a thread: a DAQ for the reader to open by its /dev/pts path."""
from __future__ import annotations

import os
import threading
import tty


class PtyWriter:
    """The pty master side: writes byte pieces from a thread (blocking writes, like the emulator)."""

    def __init__(self):
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self.path = os.ttyname(self.slave_fd)
        self.bytes_written = 0
        self.error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def write_in_thread(self, data: bytes, piece_bytes: int = 4096) -> threading.Thread:
        def run():
            try:
                view = memoryview(data)
                for start in range(0, len(data), piece_bytes):
                    piece = view[start:start + piece_bytes]
                    while piece:
                        written = os.write(self.master_fd, piece)
                        self.bytes_written += written
                        piece = piece[written:]
            except OSError as exc:
                self.error = exc

        self._thread = threading.Thread(target=run, name="pty-writer", daemon=True)
        self._thread.start()
        return self._thread

    def close_master(self) -> None:
        if self.master_fd >= 0:
            os.close(self.master_fd)
            self.master_fd = -1

    def close(self) -> None:
        self.close_master()
        if self._thread is not None:
            self._thread.join(2.0)
        if self.slave_fd >= 0:
            os.close(self.slave_fd)
            self.slave_fd = -1
