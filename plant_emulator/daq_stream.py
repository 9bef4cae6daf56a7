"""The DAQ's serial port, emulated by a pty: frames go into the master, readers open the slave.

The slave is put in raw mode and kept open by the emulator, so the device node stays valid before
(and between) readers. Readers are told a stable path, `link`: a symlink in a temporary directory the
emulator owns, pointing at the current pty, removed while the DAQ is unplugged and re-pointed when it
comes back (as udev does with /dev/serial/by-id/...), so a bench file naming it stays valid across
reconnects. Two write disciplines:

- blocking (`--speedup 0`): batches go to a writer thread through a short queue (`offer`) and are
  written completely, in order; a reader that does not read fills the pty buffer, the write waits,
  and the plant waits with it (backpressure). A DAQ does not wait for ever, though: once the writer
  has written nothing for `stall_s` of wall time while the queue is full, `offer` gives the batch up
  (STALLED) and the emulator falls back to real time, dropping what it cannot write (`drop`, counted
  in `frames_dropped`) until `write_progress_at` shows the reader reading again (process.py
  `_run_fast`). What was queued before stays and is delivered first, so the reader sees the stream
  up to the stall, then a sequence gap, as from a DAQ that overflowed;
- paced (`--speedup X > 0`): the plant runs on the wall clock like a real DAQ. `write_paced` writes
  what the pty takes at once and queues the rest for a writer thread of its own that writes
  continuously (select + write) as fast as the reader takes it, so nothing is lost while the reader
  keeps up. The queue is the DAQ's FIFO: beyond `max_pending_bytes` (the emulator sizes it in wall
  time: 0.25 s of stream at its speedup, at least 64 KiB) the oldest whole frames are dropped, as a
  real DAQ's FIFO overflows when nobody reads (the reader sees a sequence gap, an overrun, and no
  stale backlog). The stream stays frame aligned: a frame the pty has taken part of is never dropped.
"""

from __future__ import annotations

import logging
import os
import queue
import select
import shutil
import tempfile
import threading
import time
import tty

from drivers.daq_protocol import FRAME_BYTES

log = logging.getLogger(__name__)

PACED_WRITE_MAX_BYTES = 1 << 16
"""Most bytes one paced write offers the pty (it takes ~16 KiB when nobody reads)."""

QUEUED, STALLED, STOPPED = "queued", "stalled", "stopped"
"""What `offer` did with a batch."""

OFFER_POLL_S = 0.01
"""How often a waiting `offer` looks at the writer's progress and the stop flag."""


class DaqPty:
    def __init__(self, max_pending_bytes: int = 1 << 16):
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self.name = os.ttyname(self.slave_fd)
        os.set_blocking(self.master_fd, False)
        self.max_pending_bytes = max_pending_bytes
        self._pending = bytearray()  # blocking mode: what write_blocking still has to write
        self._paced = threading.Condition()  # paced mode: guards _queued (plant thread in, writer thread out)
        self._queued = bytearray()
        self._paced_writer: threading.Thread | None = None
        self._paced_stop = threading.Event()
        self.bytes_written = 0
        self.frames_dropped = 0
        self.write_progress_at = time.monotonic()  # when the pty last took bytes (the reader read)
        self._closed = False
        self._hung = False
        self._fd_lock = threading.Lock()
        self.link_dir = tempfile.mkdtemp(prefix="ripplecal-daq-")
        self.link = os.path.join(self.link_dir, "usb-ripplecal_emulated_DAQ-if00")
        self._point_link()

    def _point_link(self) -> None:
        """Re-point the stable path at the current pty, atomically (a reader never sees it half made)."""
        tmp = self.link + ".new"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(self.name, tmp)
        os.replace(tmp, self.link)

    def _remove_link(self) -> None:
        try:
            os.unlink(self.link)
        except FileNotFoundError:
            pass

    def hang_up(self) -> None:
        """Fault hook: the DAQ is unplugged. Readers of the slave get EOF/EIO; frames are discarded."""
        with self._fd_lock:
            if self._hung or self._closed:
                return
            self._hung = True
            self._pending.clear()
            with self._paced:
                self._queued.clear()
            self._remove_link()  # unplugged: the by-id path disappears too
            for fd in (self.master_fd, self.slave_fd):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def reopen(self) -> str:
        """Fault hook: the DAQ is plugged in again, as a new pty. Returns its name."""
        with self._fd_lock:
            if not self._hung:
                return self.name
            self.master_fd, self.slave_fd = os.openpty()
            tty.setraw(self.slave_fd)
            self.name = os.ttyname(self.slave_fd)
            os.set_blocking(self.master_fd, False)
            self._pending.clear()
            with self._paced:
                self._queued.clear()
            self.bytes_written = 0
            self.write_progress_at = time.monotonic()
            self._hung = False
            self._point_link()
            return self.name

    def write_blocking(self, data: bytes, stop: threading.Event) -> bool:
        """Write all of data unless `stop` is set first. Returns False if stopped."""
        self._pending += data
        while self._pending:
            if stop.is_set():
                return False
            self._flush(timeout_s=0.1)
        return True

    def start_writer(self, stop: threading.Event, depth: int = 2) -> None:
        """Blocking writes from a thread of their own, so the kernel's tty work overlaps the physics
        on a second core; `submit` blocks when `depth` batches wait (the backpressure stays)."""
        self._queue: queue.Queue[bytes] = queue.Queue(maxsize=depth)
        self._writer_stop = stop
        self._writer = threading.Thread(target=self._writer_loop, name="daq-writer", daemon=True)
        self._writer.start()

    def submit(self, data: bytes) -> bool:
        """Queue a batch for the writer thread; waits while the queue is full. False if stopped."""
        return self.offer(data) == QUEUED

    def offer(self, data: bytes, stall_s: float | None = None) -> str:
        """Queue a batch for the writer thread, waiting while the queue is full: QUEUED; STOPPED once
        the stop event is set; STALLED (the batch not queued) when stall_s is given and the pty has
        taken nothing for stall_s of wall time (nobody reads) while the queue stayed full."""
        while not self._writer_stop.is_set():
            try:
                self._queue.put(data, timeout=OFFER_POLL_S)
                return QUEUED
            except queue.Full:
                if stall_s is not None and time.monotonic() - self.write_progress_at > stall_s:
                    return STALLED
        return STOPPED

    def drop(self, data: bytes) -> None:
        """A batch the DAQ could not deliver (nobody read): counted, never written."""
        self.frames_dropped += len(data) // FRAME_BYTES

    def _writer_loop(self) -> None:
        while not self._writer_stop.is_set():
            try:
                data = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            if not self.write_blocking(data, self._writer_stop):
                return

    def write_paced(self, data: bytes) -> None:
        """Write what the pty takes now and queue the rest for the paced writer thread (started on the
        first call); never blocks. Beyond `max_pending_bytes` queued the oldest whole frames are
        dropped (an overrun)."""
        with self._fd_lock, self._paced:
            self._queued += data
            self._write_queued()
            excess = len(self._queued) - self.max_pending_bytes
            if excess > 0:
                # keep the tail of a frame the pty has taken part of, so the stream stays frame aligned
                partial = (FRAME_BYTES - self.bytes_written % FRAME_BYTES) % FRAME_BYTES
                drop = ((excess + FRAME_BYTES - 1) // FRAME_BYTES) * FRAME_BYTES
                drop = min(drop, ((len(self._queued) - partial) // FRAME_BYTES) * FRAME_BYTES)
                if drop > 0:
                    del self._queued[partial : partial + drop]
                    self.frames_dropped += drop // FRAME_BYTES
            if self._queued:
                self._paced.notify()
        if self._paced_writer is None:
            self._paced_writer = threading.Thread(target=self._paced_loop, name="daq-paced-writer", daemon=True)
            self._paced_writer.start()

    def _paced_loop(self) -> None:
        """Write the queue as soon as the pty takes it (the reader reads)."""
        while not self._paced_stop.is_set():
            with self._paced:
                if not self._queued:
                    self._paced.wait(0.1)
                    continue
            try:
                _, writable, _ = select.select([], [self.master_fd], [], 0.05)
            except (OSError, ValueError):
                writable = [True]  # the fd went with a hang-up: _write_queued drops the queue
            if writable:
                with self._fd_lock, self._paced:
                    self._write_queued()

    def _write_queued(self) -> None:
        """One non-blocking write of the queue's head (the caller holds _fd_lock and _paced)."""
        if self._closed or self._hung:
            self._queued.clear()  # unplugged: what the DAQ produces meanwhile is lost
            return
        try:
            n = os.write(self.master_fd, self._queued[:PACED_WRITE_MAX_BYTES])
        except BlockingIOError:
            return
        except OSError as exc:
            log.warning("DAQ pty write failed: %s", exc)
            self._queued.clear()
            return
        del self._queued[:n]
        self.bytes_written += n

    def _flush(self, timeout_s: float) -> None:
        if self._closed or self._hung:
            self._pending.clear()
            return
        try:
            _, writable, _ = select.select([], [self.master_fd], [], timeout_s)
        except (OSError, ValueError):
            return
        if not writable:
            return
        with self._fd_lock:
            if self._closed or self._hung:
                self._pending.clear()
                return
            try:
                n = os.write(self.master_fd, self._pending[:262144])
            except BlockingIOError:
                return
            except OSError as exc:
                log.warning("DAQ pty write failed: %s", exc)
                return
        del self._pending[:n]
        self.bytes_written += n
        if n:
            self.write_progress_at = time.monotonic()

    def close(self) -> None:
        writer = getattr(self, "_writer", None)
        if writer is not None and writer.is_alive():
            writer.join(timeout=2.0)
        self._paced_stop.set()
        with self._paced:
            self._paced.notify_all()
        if self._paced_writer is not None:
            self._paced_writer.join(timeout=2.0)
        with self._fd_lock:
            was_hung = self._hung
            self._closed = True
        for fd in () if was_hung else (self.master_fd, self.slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self.link_dir, ignore_errors=True)
