"""Which DAQ sample each drive setpoint took effect at: the drive's setpoints against the sync line.

The drive toggles the DAQ's sync input (flag bit 2) once for every setpoint it applies
(docs/interfaces.md), so `setpoints written - sync toggles seen` is the number of setpoints still
pending, and the sample at which the last one toggled is where it took effect. That count needs a
known base. It is certain while the stream is read without a hole whenever a setpoint is pending,
and it stays certain across idle: nothing writes a setpoint while no run holds the bench, so the
line keeps its level (checked when the next run starts). It is in doubt at connect (what did a
previous master leave pending?), after a DAQ gap or flush while setpoints were pending, after a
drive fault (the drive drops what it had queued), after a write whose answer was lost, and after a
run that failed in the middle: then it is established again, and only then.

Establishing it: with nothing written, read until the line has been quiet for `quiet_samples()`
(on the DAQ sample clock); quiet that long means nothing is pending, so the count is taken as the
drive's. The window is sized from the DAQ path's real buffering: every confirmed setpoint measures
how far past the newest sample read at its write its toggle came (path backlog + the drive's
reaction), and the window is twice the largest of the recent ones. Before any setpoint was timed
(at connect) it is INITIAL_QUIET_SAMPLES, the deepest DAQ path we know of (the emulator run as
fast as it is read holds about 16000 samples between its plant and the reader).
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from drivers.daq_protocol import FLAG_SYNC_INPUT, DecodedSamples
from drivers.daq_reader import DaqReader
from service.errors import BenchFailed

log = logging.getLogger(__name__)

INITIAL_QUIET_SAMPLES = 20480  # 1.28 s at 16 kHz; only until the first setpoint was timed
MIN_QUIET_SAMPLES = 512  # never less: the emulator applies one queued setpoint per 256-sample chunk
QUIET_PER_LATENCY = 2.0  # the window spans twice the largest recent setpoint latency
LATENCIES_KEPT = 64
MAX_ESTABLISH_SAMPLES = 131072  # a line that toggles for 8 s of plant time with nothing written is not ours
# never longer: a latency measured while the reader lagged far behind the stream (a loaded PC) would ask for
# a window that no gap may interrupt for most of MAX_ESTABLISH_SAMPLES; the drive's commit counter read back
# at the end of establishing (resync) is the check on a window that was too short
MAX_QUIET_SAMPLES = MAX_ESTABLISH_SAMPLES // 4


class AccountingError(BenchFailed, RuntimeError):
    """The setpoint count could not be established (the line never went quiet)."""


@dataclass
class Chunk:
    samples: DecodedSamples
    toggle_offsets: np.ndarray  # offsets within the chunk where the sync level changed
    gap_offsets: np.ndarray  # offsets of samples with lost samples or a bad frame just before them


class DaqCursor:
    """In-order consumer of a DaqReader that counts sync toggles.

    Across a gap (samples lost: the reader fell behind a DAQ that cannot wait) only the level change is
    seen, so the count stays exact in parity but misses toggles in pairs; `count_hidden_toggles` adds
    them once the caller has shown they happened (OperatingPointSession.wait_for_effect).
    `on_toggles(first_number, indices)` hears every toggle counted, with its running number."""

    def __init__(
        self, reader: DaqReader, read_timeout_s: float, on_toggles: Callable[[int, np.ndarray], None] | None = None
    ):
        self.reader = reader
        self.read_timeout_s = read_timeout_s
        self.on_toggles = on_toggles
        self.toggles_seen = 0
        self.toggles_hidden = 0  # added by count_hidden_toggles: lost in gaps, for the log and the run
        self.gaps_seen = 0
        self.last_index = -1
        self._level: int | None = None

    def read(self, n: int) -> Chunk:
        """Exactly the next n samples."""
        return self._counted(self.reader.read(n, self.read_timeout_s))

    def read_available(self, max_n: int) -> Chunk:
        """The next 1..max_n samples, as soon as one is there (what the reader holds, up to max_n)."""
        return self._counted(self.reader.read_available(max_n, self.read_timeout_s))

    def _counted(self, samples: DecodedSamples) -> Chunk:
        level = (samples.flags & FLAG_SYNC_INPUT) != 0
        prev = np.empty_like(level)
        prev[1:] = level[:-1]
        prev[0] = level[0] if self._level is None else bool(self._level)
        toggles = np.flatnonzero(level != prev)
        self._level = int(level[-1])
        first = self.toggles_seen + 1
        self.toggles_seen += len(toggles)
        gaps = np.flatnonzero(samples.gap_before)
        self.gaps_seen += len(gaps)
        self.last_index = int(samples.index[-1])
        if len(toggles) and self.on_toggles is not None:
            self.on_toggles(first, samples.index[toggles])
        return Chunk(samples, toggles, gaps)

    def discard_buffered(self) -> int:
        """Drop what the reader and the port hold; returns the samples dropped. Toggles in them are
        not seen: only safe while nothing is pending (SetpointAccounting.flush)."""
        return self.reader.discard_buffered(flush_port=True)

    def count_hidden_toggles(self, n: int) -> None:
        """n toggles happened inside gaps of the stream (an even number: the parity was seen)."""
        self.toggles_seen += n
        self.toggles_hidden += n


class SetpointAccounting:
    """The drive's setpoints against the DAQ's sync toggles, for the life of a bench connection.

    setpoints_written(): setpoints the drive accepted so far (drivers.drive.DriveClient);
    resync_drive(toggles_seen): takes the count as the drive's once nothing is pending (reads back
    its commit counter); note_write(number) is to be called after each setpoint write (the drive
    client's listener), so that its toggle's latency can be measured."""

    def __init__(
        self,
        reader: DaqReader,
        read_timeout_s: float,
        setpoints_written: Callable[[], int],
        resync_drive: Callable[[int], dict[str, Any]],
    ):
        self.cursor = DaqCursor(reader, read_timeout_s, on_toggles=self._on_toggles)
        self._setpoints_written = setpoints_written
        self._resync_drive = resync_drive
        self.doubt_reason: str | None = "not established since the bench was connected"
        self._write_marks: dict[int, int] = {}  # setpoint number -> newest sample read at its write
        self.latencies: collections.deque[int] = collections.deque(
            maxlen=LATENCIES_KEPT
        )  # samples from write to its toggle
        self.establishments = 0

    # --- the count -------------------------------------------------------------------------------
    @property
    def in_doubt(self) -> bool:
        return self.doubt_reason is not None

    def doubt(self, reason: str) -> None:
        """The count can no longer be trusted (the first reason is kept until it is re-established)."""
        if self.doubt_reason is None:
            log.info("setpoint accounting in doubt: %s", reason)
            self.doubt_reason = reason
        self._write_marks.clear()  # toggles no longer match their writes by number: time none of them

    def pending(self) -> int:
        """Setpoints written whose toggle has not been seen yet."""
        return self._setpoints_written() - self.cursor.toggles_seen

    # --- latency ---------------------------------------------------------------------------------
    def note_write(self, number: int) -> None:
        """Setpoint `number` was just written: remember how far the stream had been read."""
        if self.in_doubt:
            return
        self._write_marks[number] = self.cursor.last_index
        if len(self._write_marks) > 4 * LATENCIES_KEPT:  # toggles lost in gaps leave marks behind
            for stale in sorted(self._write_marks)[:-LATENCIES_KEPT]:
                del self._write_marks[stale]

    def _on_toggles(self, first_number: int, indices: np.ndarray) -> None:
        if self.in_doubt:
            return
        for k, index in enumerate(indices):
            mark = self._write_marks.pop(first_number + k, None)
            if mark is not None and mark >= 0:
                self.latencies.append(int(index) - mark)
        for number in [n for n in self._write_marks if n < first_number]:
            del self._write_marks[number]  # their toggles were hidden in gaps: no latency to learn

    def quiet_samples(self) -> int:
        """Quiet (no toggle, no gap) that shows nothing is pending: twice the largest recent setpoint
        latency, at least MIN_QUIET_SAMPLES, at most MAX_QUIET_SAMPLES; INITIAL_QUIET_SAMPLES before any
        was measured."""
        if not self.latencies:
            return INITIAL_QUIET_SAMPLES
        return min(MAX_QUIET_SAMPLES, max(MIN_QUIET_SAMPLES, int(QUIET_PER_LATENCY * max(self.latencies))))

    # --- runs ------------------------------------------------------------------------------------
    def start_run(self, guard: Callable[[], None]) -> None:
        """Before a run writes its first setpoint: drop the stale data the DAQ path holds (safe only
        with nothing pending, else the count goes in doubt), then check on fresh data that the line
        kept its level (a toggle with nothing written means someone else moved it)."""
        if self.in_doubt:
            return
        if self.pending() != 0:
            self.doubt(f"{self.pending()} setpoint(s) unconfirmed when the last run ended")
            return
        self.cursor.discard_buffered()
        before = self.cursor.toggles_seen
        guard()
        self.cursor.read_available(256)
        if self.cursor.toggles_seen != before:
            self.doubt("the DAQ sync line changed level while no setpoint was written")

    def end_run(self) -> None:
        """After a run: setpoints still unconfirmed leave the count in doubt for the next one."""
        if self.pending() != 0:
            self.doubt(f"{self.pending()} setpoint(s) unconfirmed when the run ended")

    def establish(self, guard: Callable[[], None]) -> dict[str, Any]:
        """Re-establish the count with nothing being written (module doc). Returns what it took:
        {quiet_samples, waited_samples, reason}; raises AccountingError if the line never goes quiet."""
        reason = self.doubt_reason
        quiet_needed = self.quiet_samples()
        self.cursor.discard_buffered()
        start: int | None = None
        last_event = 0  # index of the last toggle or gap (set with start, at the first chunk)
        while True:
            guard()
            chunk = self.cursor.read_available(4096)
            index = chunk.samples.index
            if start is None:
                start = int(index[0])
                last_event = start
            events = np.union1d(chunk.toggle_offsets, chunk.gap_offsets)
            if len(events):
                last_event = int(index[int(events[-1])])
            if int(index[-1]) - last_event >= quiet_needed:
                break
            if int(index[-1]) - start > MAX_ESTABLISH_SAMPLES:
                raise AccountingError(
                    f"the DAQ sync line never stayed quiet for {quiet_needed} samples in "
                    f"{int(index[-1]) - start} samples with no setpoint written "
                    f"({self.cursor.toggles_seen} toggles): setpoints cannot be counted"
                )
        report = self._resync_drive(self.cursor.toggles_seen)
        if report.get("commits_expected") is not None and report["commits_expected"] != report["commits_reported"]:
            log.warning(
                "drive commit counter %d, expected %d: setpoint count re-established from the drive",
                report["commits_reported"],
                report["commits_expected"],
            )
        self._write_marks.clear()
        self.doubt_reason = None
        self.establishments += 1
        waited = int(self.cursor.last_index) - start + 1
        log.info("setpoint accounting established (%s): quiet %d samples, %d read", reason, quiet_needed, waited)
        return {"quiet_samples": quiet_needed, "waited_samples": waited, "reason": reason}
