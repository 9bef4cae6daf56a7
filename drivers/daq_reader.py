"""DAQ stream reader: one thread reads the serial port, decodes what arrived, and queues the samples.

The DAQ sample counter is the clock of every measurement, so the reader must not lose or reorder
samples and must say where the stream had a hole (gap_before). It also provides backpressure: the
thread stops reading while `max_buffered_samples` are unconsumed. Against the emulator in
`--speedup 0` the plant waits for its pty write, so it runs only as fast as it is consumed (after
0.25 s without a read it goes on in real time and drops frames, as a real DAQ overflows), and memory
stays bounded on a real DAQ too (the DAQ then overflows, which shows up as whole frames missing
after the pause: counted as `overruns`, not as line errors).

Read discipline: the thread waits (up to SERIAL_READ_TIMEOUT_S) for the first byte, then takes what
the port holds, and goes on taking while more is waiting, up to the room left in the queue and
COALESCE_MAX_BYTES. In real time each small arrival (a USB transfer, an emulator write every ~2 ms)
is decoded and handed over at once, so a sample reaches the consumer within a few ms of reaching the
port; a backlog (the emulator at `--speedup 0` runs ~300x real time) is decoded in large batches,
since decoding (vectorised in drivers.daq_protocol.FrameDecoder) has a fixed cost per call.

Counters: `crc_failures` and `sequence_gaps` are line errors only. The thread knows when it flushed
the port (discard_buffered(flush_port=True)) and when it paused for backpressure, and tells the
decoder, which counts the resync and jump right after a flush as `flush_*` and whole frames missing
after a pause as `overruns` (DecoderCounters; all of them in health()).

Reconnect: when the port fails (EOF, EIO: the DAQ was unplugged) the thread closes it and reopens
the same URL with backoff (as /dev/serial/by-id/... reappears when a USB DAQ comes back). While it
is away, read() raises DaqDisconnected at once, and so does a read that was waiting when it went; the
first samples after a reconnect are marked gap_before, so no window spans the hole.

One reader per DAQ: a serial port or pty (a device path) is opened with an exclusive lock (pyserial's
`exclusive=True`: flock on POSIX), so a second reader of the same port, in this process or another
(a second `ripplecal serve`, a CLI run with --bench), fails at start with DaqPortBusy naming the port
instead of taking half of the frames. URLs (socket://, loop://, ...) have no such lock.

What the port holds when it is first opened was streamed while nobody read: whole frames missing in
it are the DAQ's overruns (as after a backpressure pause), not line errors.

Frame rate (`check_frame_rate`, at connect): the sequence numbers' advance over the wall clock (the
slope over every arrival in the window), from the first fresh frame on, against the rate the DAQ is
configured at. Only a stream paced by its own
clock can be judged so: one that streams as fast as it is read (the emulator at `--speedup 0`, which
waits for its reader) says nothing about its sample clock; a stream over FREE_RUNNING_RATIO times
the rate it should have is taken for one (`FrameRateCheck.judged` False) rather than called wrong.
A rate outside FRAME_RATE_TOLERANCE is measured once more over a longer window before it is called
wrong (a loaded PC's hiccup at either end of a short window is not a wrong rate).
"""

from __future__ import annotations

import collections
import dataclasses
import errno
import fcntl
import os
import select
import stat
import struct
import termios
import threading
import time

import numpy as np
import serial

from drivers.daq_protocol import FLAG_SENSOR_FAULT, FRAME_BYTES, DecodedSamples, DecoderCounters, FrameDecoder
from drivers.errors import (
    DaqDisconnected,
    DaqNotSerialPort,
    DaqNotStreaming,
    DaqPortBusy,
    DaqRateMismatch,
    DaqTimeout,
)

__all__ = [
    "DaqReader",
    "DaqTimeout",
    "DaqDisconnected",
    "DaqPortBusy",
    "DaqNotSerialPort",
    "DaqNotStreaming",
    "DaqRateMismatch",
    "DecodedSamples",
    "DecoderCounters",
    "FrameRateCheck",
]

SERIAL_READ_TIMEOUT_S = 0.05
"""pyserial read timeout: how long the thread waits for a first byte; bounds how long it takes to
notice close() or freed space."""

COALESCE_MAX_BYTES = 1 << 18
"""Most bytes decoded in one batch when the port has a backlog (about 22000 samples)."""

DEFAULT_BAUDRATE = 2_000_000
"""16 kHz x 12 bytes x 10 bit = 1.92 Mbit/s; ignored by ptys, sockets and USB CDC devices."""

RECONNECT_BACKOFF_S = (0.05, 0.5)
"""First and longest pause between attempts to reopen a lost port (doubling in between)."""

FRAME_RATE_SETTLE_S = 0.1
"""check_frame_rate reads this long before its window starts: the backlog the port held arrives in it."""

FRAME_RATE_WINDOW_S = 0.5
"""Wall time over which the frame rate is measured (what a healthy bench pays at connect) ..."""

FRAME_RATE_CONFIRM_S = 2.0
"""... and the longer window that confirms a rate outside the tolerance before it is called wrong."""

FRAME_RATE_TOLERANCE = 0.20
"""A measured rate within +-20 % of the expected one passes: a wide margin for a loaded PC (at load 8 on
2 cores the slope measured within 1 % of a paced pty and of the emulator at --speedup 1; taken from
the window's two ends alone it was up to 19 % off: tests/benchmarks/bench_daq_rate.py), narrow enough
for the settings people get wrong (a factor of 2; 8 vs 10 kHz, 25 %)."""

FREE_RUNNING_RATIO = 5.0
"""A stream over this many times its expected rate is taken as one that streams as fast as it is read
(not judged); a paced DAQ set wrong by a factor up to 5 is still called wrong."""

FRAME_RATE_MIN_ELAPSED_S = 0.05
"""A free-running stream is recognised after this much of the window (no need to decode a whole
window of it)."""


@dataclasses.dataclass(frozen=True)
class FrameRateCheck:
    """What check_frame_rate found: measured_hz (frames per wall second, from the sequence numbers),
    expected_hz, and judged (False: a stream as fast as it is read, whose rate says nothing)."""

    measured_hz: float
    expected_hz: float
    judged: bool


def rate_text(hz: float) -> str:
    """A rate as people say it: three significant digits (16023.4 -> '16000')."""
    return f"{float(f'{hz:.3g}'):g}"


class DaqReader:
    """Reads DAQ frames from any pyserial URL (/dev/ttyACM0, /dev/pts/N, socket://host:port, loop://).

    max_buffered_samples: the thread pauses reading when this many samples wait unconsumed (a pending
    read(n) with a larger n raises the limit to n for its duration so it can complete).
    read_chunk_bytes: the most bytes one serial read call asks for (a backlog is read in several
    calls and decoded as one batch of up to COALESCE_MAX_BYTES).
    """

    def __init__(
        self,
        url: str,
        max_buffered_samples: int = 16384,
        read_chunk_bytes: int = 8192,
        baudrate: int = DEFAULT_BAUDRATE,
        reconnect: bool = True,
    ):
        if max_buffered_samples < 1:
            raise ValueError(f"max_buffered_samples must be >= 1, got {max_buffered_samples}")
        if read_chunk_bytes < FRAME_BYTES:
            raise ValueError(f"read_chunk_bytes must be >= {FRAME_BYTES}, got {read_chunk_bytes}")
        self.url = url
        self.max_buffered_samples = max_buffered_samples
        self.read_chunk_bytes = read_chunk_bytes
        self.baudrate = baudrate
        self.reconnect = reconnect
        self._port: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._cond = threading.Condition()
        self._blocks: collections.deque[DecodedSamples] = collections.deque()
        self._buffered = 0
        self._flush_requested = False
        self._flushes = 0
        self._demand = 0
        self._stop = False
        self._running = False
        self._error: BaseException | None = None
        self._connected = False
        self._mark_gap = False
        self._disconnects = 0  # a read that saw this change while waiting has a hole in it
        self._reconnects = 0
        self._last_data_monotonic: float | None = None
        self._sensor_fault_samples = 0
        self._counters = DecoderCounters()
        self._bytes_read = 0
        self._samples_delivered = 0

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> "DaqReader":
        """Open the port and start the reader thread. Raises DaqPortBusy when another reader holds the
        port's exclusive lock (serial.SerialException if it cannot be opened at all)."""
        if self._thread is not None:
            raise RuntimeError(f"DAQ reader for {self.url} already started")
        self._port = self._open()
        self._stop = False
        self._running = True
        self._connected = True
        self._thread = threading.Thread(target=self._run, name=f"daq-reader {self.url}", daemon=True)
        self._thread.start()
        return self

    def close(self, join_timeout_s: float = 2.0) -> None:
        """Stop the thread (joined with a timeout) and close the port. Idempotent."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        port = self._port
        if port is not None and hasattr(port, "cancel_read"):
            try:
                port.cancel_read()
            except Exception:  # noqa: BLE001 - best effort wake-up, the read timeout also ends it
                pass
        thread = self._thread
        if thread is not None:
            thread.join(join_timeout_s)
        self._close_port()

    def __enter__(self) -> "DaqReader":
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- reader thread ------------------------------------------------------------------------------
    def _open(self) -> serial.SerialBase:
        """The port, locked for this reader alone where the OS can (a device path on POSIX); DaqPortBusy
        when another reader holds that lock."""
        lockable = "://" not in self.url and os.name == "posix"
        try:
            return serial.serial_for_url(
                self.url,
                timeout=SERIAL_READ_TIMEOUT_S,
                baudrate=self.baudrate,
                **({"exclusive": True} if lockable else {}),
            )
        except serial.SerialException as exc:
            if lockable and exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise DaqPortBusy(
                    f"DAQ {self.url}: another process holds this port (its exclusive lock is taken): one "
                    "reader per DAQ; is another ripplecal (serve, or identify / sweep / maps download with "
                    "--bench) reading it? Stop that one first"
                ) from exc
            not_a_port = _not_a_serial_port(self.url) if lockable else None
            if not_a_port is not None:
                raise DaqNotSerialPort(f"DAQ {self.url} {not_a_port}, not a serial port") from exc
            raise

    def _run(self) -> None:
        decoder = FrameDecoder()
        # the OS buffered the stream while nobody read: frames missing in that backlog are overruns
        decoder.note_pause()
        try:
            while True:
                try:
                    self._read_port(decoder)
                    return  # close() asked
                except BaseException as exc:  # noqa: BLE001 - reported to the consumer as DaqDisconnected
                    with self._cond:
                        if self._stop:
                            return
                        self._error = exc
                        self._connected = False
                        self._disconnects += 1
                        self._cond.notify_all()
                    self._close_port()
                    if not self.reconnect or not self._reopen_with_backoff():
                        return
                    decoder.note_reconnect()  # its hole is the disconnect's
        finally:
            with self._cond:
                self._running = False
                self._connected = False
                self._cond.notify_all()

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - the port is already gone (EIO)
                pass

    def _reopen_with_backoff(self) -> bool:
        """Reopen the same URL until it works or close() is called. True once reopened."""
        pause = RECONNECT_BACKOFF_S[0]
        while True:
            with self._cond:
                if self._cond.wait_for(lambda: self._stop, timeout=pause):
                    return False
            try:
                port = self._open()
            except Exception as exc:  # noqa: BLE001 - not back yet: keep the cause for the status
                with self._cond:
                    self._error = exc
                pause = min(pause * 2, RECONNECT_BACKOFF_S[1])
                continue
            with self._cond:
                if self._stop:
                    port.close()
                    return False
                self._port = port
                self._connected = True
                self._reconnects += 1
                self._mark_gap = True
                self._cond.notify_all()
            return True

    def _read_port(self, decoder: FrameDecoder) -> None:
        port = self._port
        assert port is not None
        cond = self._cond
        while True:
            with cond:
                paused = False
                while (
                    not self._stop
                    and not self._flush_requested
                    and self._buffered >= max(self.max_buffered_samples, self._demand)
                ):
                    paused = True
                    cond.wait(SERIAL_READ_TIMEOUT_S)
                    # paused by backpressure we read nothing, so look for an unplugged port directly
                    self._check_port(port)
                if self._stop:
                    return
                flush_now = self._flush_requested
                room = max(self.max_buffered_samples, self._demand) - self._buffered
            if paused:
                # a DAQ streams on while we do not read: whole frames missing next are an overrun
                decoder.note_pause()
            if flush_now:
                # done here, by the thread that reads: flushing under a blocked read breaks pyserial
                try:
                    port.reset_input_buffer()
                except (OSError, serial.SerialException, AttributeError):
                    pass  # not every pyserial URL type can flush
                decoder.note_flush()  # the resync and jump at the next frame are this flush's
                with cond:
                    self._flush_requested = False
                    self._flushes += 1
                    cond.notify_all()
                continue
            # never read more than fits: that is what lets the writer block (backpressure)
            chunk = self._read_available(port, min(room * FRAME_BYTES, COALESCE_MAX_BYTES))
            if not chunk:
                continue
            samples = decoder.feed(chunk)
            counters = dataclasses.replace(decoder.counters)
            sensor_faults = int(np.count_nonzero(samples.flags & FLAG_SENSOR_FAULT)) if len(samples) else 0
            with cond:
                self._sensor_fault_samples += sensor_faults
                if len(samples):
                    if self._mark_gap:
                        # the stream has a hole where the DAQ was away
                        samples.gap_before[0] = True
                        self._mark_gap = False
                    self._blocks.append(samples)
                    self._buffered += len(samples)
                self._counters = counters
                self._bytes_read += len(chunk)
                self._last_data_monotonic = time.monotonic()
                cond.notify_all()

    def _read_available(self, port: serial.SerialBase, cap_bytes: int) -> bytes:
        """Wait up to SERIAL_READ_TIMEOUT_S for the first byte, then take what the port holds, and go
        on while more is waiting (a backlog), up to cap_bytes. Returns b"" on timeout.

        Never a read of more than is there: pyserial would block until all of it arrived (or its
        timeout), holding back the samples that did."""
        first = port.read(1)
        if not first:
            return first
        parts = [first]
        total = 1
        while total < cap_bytes:
            waiting = _bytes_waiting(port)
            if waiting <= 0:
                break
            more = port.read(min(waiting, cap_bytes - total, self.read_chunk_bytes))
            if not more:
                break
            parts.append(more)
            total += len(more)
        return b"".join(parts)

    def _check_port(self, port: serial.SerialBase) -> None:
        """Raise if the port has hung up (poll: POLLHUP/POLLERR) or its device path has gone."""
        if "://" not in self.url and not os.path.exists(self.url):
            raise serial.SerialException(f"{self.url} has disappeared (device unplugged)")
        fileno = getattr(port, "fileno", None)
        if fileno is None:
            return
        try:
            fd = fileno()
            poller = select.poll()
            poller.register(fd, select.POLLIN)
            events = poller.poll(0)
        except (OSError, ValueError, serial.SerialException):
            return
        if any(ev & (select.POLLHUP | select.POLLERR | select.POLLNVAL) for _, ev in events):
            raise serial.SerialException(f"{self.url} hung up")

    # -- consumer side ------------------------------------------------------------------------------
    def read(self, n: int, timeout_s: float) -> DecodedSamples:
        """The next n samples in stream order (blocks joined or split as needed).

        Raises DaqTimeout if fewer than n arrived within timeout_s (the ones that did arrive stay queued
        for the next read), DaqDisconnected if the reader thread has stopped and fewer than n are left.
        """
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        with self._cond:
            self._demand = n
            self._cond.notify_all()
            try:
                self._wait_buffered(n, timeout_s, lambda: f"only {self._buffered} of {n} samples arrived")
                return self._take(n)
            finally:
                self._demand = 0
                self._cond.notify_all()

    def read_available(self, max_n: int, timeout_s: float) -> DecodedSamples:
        """Between 1 and max_n samples in stream order: whatever is queued (at most max_n) as soon as
        at least one sample is, waiting up to timeout_s for the first.

        Raises DaqTimeout if none arrived within timeout_s, DaqDisconnected if the reader thread has
        stopped or the port was lost (while waiting, or before) and nothing is queued.
        """
        if max_n < 1:
            raise ValueError(f"max_n must be >= 1, got {max_n}")
        with self._cond:
            self._wait_buffered(1, timeout_s, lambda: "no sample arrived")
            taken = self._take(min(max_n, self._buffered))
            self._cond.notify_all()  # room freed: a reader thread paused for backpressure goes on
            return taken

    def _wait_buffered(self, n: int, timeout_s: float, shortfall) -> None:
        """Wait (the condition held) until n samples are queued; DaqDisconnected if the reader stops or
        its port is lost meanwhile, DaqTimeout after timeout_s (`shortfall()` says what came)."""
        if self._thread is None:
            raise DaqDisconnected(f"DAQ reader for {self.url} was not started (call start())")
        deadline = time.monotonic() + timeout_s
        disconnects = self._disconnects
        while self._buffered < n:
            if not self._running or not self._connected or self._disconnects != disconnects:
                raise DaqDisconnected(self._disconnected_message(n))
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                raise DaqTimeout(
                    f"DAQ {self.url}: {shortfall()} within {timeout_s:g} s "
                    f"({self._bytes_read} bytes read so far, decoder {self._counters})"
                )
            self._cond.wait(remaining_s)

    def _disconnected_message(self, n: int) -> str:
        if self._error is not None:
            cause = f"{type(self._error).__name__}: {self._error}"
        elif self._stop:
            cause = "reader closed"
        elif self._running and self.reconnect:
            cause = "port lost; reopening"
        else:
            cause = "reader thread ended"
        again = "; reopening it with backoff" if self._running and self.reconnect and not self._stop else ""
        return (
            f"DAQ {self.url} disconnected ({cause}){again}; {self._buffered} of {n} requested samples were "
            f"left after {self._samples_delivered} delivered"
        )

    def _take(self, n: int) -> DecodedSamples:
        """Pop exactly n samples (caller holds the lock and has checked that n are buffered)."""
        if n == 0:
            return DecodedSamples.empty()
        parts: list[DecodedSamples] = []
        needed = n
        while needed:
            head = self._blocks[0]
            if len(head) <= needed:
                parts.append(self._blocks.popleft())
                needed -= len(head)
            else:
                parts.append(head.slice(0, needed))
                self._blocks[0] = head.slice(needed)
                needed = 0
        self._buffered -= n
        self._samples_delivered += n
        return DecodedSamples.concat(parts)

    def discard_buffered(self, flush_port: bool = False) -> int:
        """Drop every queued sample (e.g. stale data from before a setpoint); returns how many.
        flush_port also drops what the OS holds for the port (the next frame then starts with a
        resynchronisation, which marks a gap; the counters count it as the flush's, flush_*, not as
        a line error)."""
        with self._cond:
            if flush_port and self._running:
                self._flush_requested = True
                self._cond.notify_all()
                self._cond.wait_for(lambda: not self._flush_requested or not self._running, timeout=2.0)
            dropped = self._buffered
            self._samples_delivered += dropped
            self._blocks.clear()
            self._buffered = 0
            self._cond.notify_all()
            return dropped

    # -- frame rate ---------------------------------------------------------------------------------
    def wait_first_frame(self, timeout_s: float) -> None:
        """A frame arrives within timeout_s (left queued), else DaqNotStreaming: the port opened, but
        is it the DAQ's, and is the DAQ streaming?"""
        try:
            with self._cond:
                self._wait_buffered(1, timeout_s, lambda: "no frame arrived")
        except DaqTimeout as exc:
            raise self._not_streaming(timeout_s) from exc

    def _not_streaming(self, timeout_s: float) -> DaqNotStreaming:
        return DaqNotStreaming(
            f"DAQ {self.url}: the port opened but no frame came within {timeout_s:g} s "
            f"({self.bytes_read} bytes read, decoder {self.counters}): is it the DAQ's port, and is the DAQ streaming?"
        )

    def measure_frame_rate(
        self, window_s: float, first_frame_timeout_s: float, stop_above_hz: float | None = None
    ) -> float:
        """Frames per second of wall time, from the sequence numbers over window_s (frames the DAQ
        streamed but the line lost count too), from the first fresh frame on: what was queued is
        dropped and FRAME_RATE_SETTLE_S read first, so the port's backlog is not taken for a burst.
        Consumes what it reads. stop_above_hz: return early once the rate is surely above it.
        DaqNotStreaming when no frame comes within first_frame_timeout_s (or the stream stops)."""
        self.discard_buffered()
        try:
            last = self.read_available(1 << 16, first_frame_timeout_s)
            settle_until = time.monotonic() + FRAME_RATE_SETTLE_S
            while time.monotonic() < settle_until:
                last = self.read_available(1 << 16, first_frame_timeout_s)
            start_at, start_index = time.monotonic(), int(last.index[-1])
            # (wall time, frames since the start) at each arrival: the slope over all of them, not the two
            # ends alone, so that one late wake-up of a loaded PC at either end does not make the rate
            arrivals_s, counts = [0.0], [0]
            while True:
                last = self.read_available(1 << 16, first_frame_timeout_s)
                elapsed_s = time.monotonic() - start_at
                frames = int(last.index[-1]) - start_index
                arrivals_s.append(elapsed_s)
                counts.append(frames)
                if elapsed_s >= window_s:
                    return float(np.polyfit(arrivals_s, counts, 1)[0]) if len(counts) >= 3 else frames / elapsed_s
                if stop_above_hz is not None and elapsed_s >= FRAME_RATE_MIN_ELAPSED_S:
                    # even if the window's end came at once, the rate would stay above stop_above_hz
                    if frames / window_s > stop_above_hz:
                        return frames / elapsed_s
        except DaqTimeout as exc:
            raise self._not_streaming(first_frame_timeout_s) from exc

    def check_frame_rate(self, expected_hz: float, first_frame_timeout_s: float) -> FrameRateCheck:
        """The DAQ streams at expected_hz (frames per wall second), within FRAME_RATE_TOLERANCE: else
        DaqRateMismatch naming both rates, after a confirming FRAME_RATE_CONFIRM_S window. A stream over
        FREE_RUNNING_RATIO x expected_hz is not judged (module doc). DaqNotStreaming if none comes."""
        if not expected_hz > 0:
            raise ValueError(f"expected_hz must be > 0, got {expected_hz!r}")
        free_running_hz = FREE_RUNNING_RATIO * expected_hz
        measured = self.measure_frame_rate(FRAME_RATE_WINDOW_S, first_frame_timeout_s, free_running_hz)
        for confirm in (False, True):
            if measured > free_running_hz:
                return FrameRateCheck(measured, expected_hz, judged=False)
            if abs(measured / expected_hz - 1.0) <= FRAME_RATE_TOLERANCE:
                return FrameRateCheck(measured, expected_hz, judged=True)
            if not confirm:
                measured = self.measure_frame_rate(FRAME_RATE_CONFIRM_S, first_frame_timeout_s, free_running_hz)
        raise DaqRateMismatch(
            f"DAQ {self.url} streams {rate_text(measured)} frames/s, {rate_text(expected_hz)} expected",
            measured,
            expected_hz,
        )

    # -- introspection ------------------------------------------------------------------------------
    @property
    def counters(self) -> DecoderCounters:
        """Snapshot of the decoder's counters, consistent with the queue: line errors (crc_failures,
        sequence_gaps, ...) apart from flush_* and overruns (see DecoderCounters)."""
        with self._cond:
            return dataclasses.replace(self._counters)

    @property
    def buffered_samples(self) -> int:
        with self._cond:
            return self._buffered

    @property
    def bytes_read(self) -> int:
        with self._cond:
            return self._bytes_read

    @property
    def running(self) -> bool:
        with self._cond:
            return self._running

    @property
    def error(self) -> BaseException | None:
        """The last port error (why it was lost, or why reopening it failed); kept after a reconnect."""
        with self._cond:
            return self._error

    @property
    def connected(self) -> bool:
        """The port is open and being read (False while it is lost and being reopened)."""
        with self._cond:
            return self._running and self._connected

    def health(self) -> dict:
        """Per-device truth for the bench status: connected, last error, data age, reconnects, and the
        decoder's counters: line errors (crc_failures, sequence_gaps, samples_lost, bytes_skipped,
        resyncs) apart from what the reader's own flushes discarded (flushes, flush_resyncs,
        flush_bytes_skipped, flush_samples_lost) and overruns after a backpressure pause (overruns,
        overrun_samples_lost)."""
        with self._cond:
            age = None if self._last_data_monotonic is None else time.monotonic() - self._last_data_monotonic
            err = self._error
            return {
                **dataclasses.asdict(self._counters),
                "flushes": self._flushes,
                "url": self.url,
                "connected": self._running and self._connected,
                "last_error": None if err is None else f"{type(err).__name__}: {err}",
                "data_age_s": None if age is None else round(age, 3),
                # stale: room to read, yet nothing came for a second (a full buffer is backpressure, not staleness)
                "stale": bool(
                    self._connected
                    and (age is None or age > 1.0)
                    and self._buffered < max(self.max_buffered_samples, self._demand)
                ),
                "reconnects": self._reconnects,
                "sensor_fault_samples": self._sensor_fault_samples,
                "disconnects": self._disconnects,
                "buffered_samples": self._buffered,
            }


def _not_a_serial_port(path: str) -> str | None:
    """What the path is when it cannot be a serial port ('is a regular file'), None when it may be one
    (a terminal, or nothing there: the open's own error says that)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode):
        return "is a regular file"
    if stat.S_ISDIR(mode):
        return "is a directory"
    if stat.S_ISCHR(mode):
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
        except OSError:
            return None
        try:
            return None if os.isatty(fd) else "is a character device that is not a terminal"
        finally:
            os.close(fd)
    return "is neither a terminal nor a regular file"


def _bytes_waiting(port: serial.SerialBase) -> int:
    """Bytes the port holds now. FIONREAD on its descriptor where it has one (a tty, a socket: pyserial's
    socket:// in_waiting only says 0 or 1), else pyserial's in_waiting (loop://)."""
    try:
        fd = port.fileno()
    except (AttributeError, OSError, ValueError):
        return port.in_waiting
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
