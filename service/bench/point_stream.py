"""The DAQ stream of one operating point, consumed in order.

`PointStream` hands out the DAQ samples of one point in order and finds the exact sample at which
each setpoint took effect (the drive's sync toggles, service/bench/setpoint_accounting.py); what it
hands out is counted on its `PlantClock` (service/bench/plant_clock.py): plant time from each
effect, stale before it (on a real bench CAN and DAQ latency, in the emulator run as fast as it is
read its buffered data).

A `recorder` (service.store.recordings.RunRecorder), while set, receives every sample the stream
consumes, marked counted or stale as above.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from drivers.daq_protocol import DecodedSamples
from service.bench.contracts import Recorder
from service.bench.plant_clock import PlantClock
from service.bench.setpoint_accounting import Chunk, SetpointAccounting
from service.identification.session import MeasurementError

log = logging.getLogger(__name__)


class PointStream:
    """The DAQ stream of one operating point, in order, on the DAQ sample clock (module doc)."""

    CHUNK_SAMPLES = 4096  # the most one read takes while looking for a toggle

    def __init__(self, accounting: SetpointAccounting, sample_rate_hz: float, guard: Callable[[], None] | None = None):
        self.accounting = accounting
        self.cursor = accounting.cursor
        self.clock = PlantClock(sample_rate_hz)
        self.guard = guard  # called before every DAQ read; raises to stop the run (cancel, interlock)
        self._pending: DecodedSamples | None = None  # samples read past the point we needed
        self._hidden_before = self.cursor.toggles_hidden
        self.recorder: Recorder | None = None  # set for the method's duration by identify_at (raw recording)

    @property
    def sample_rate_hz(self) -> float:
        return self.clock.sample_rate_hz

    @property
    def toggles_hidden(self) -> int:
        """Setpoint toggles of this point that fell into DAQ gaps and were counted once the line was quiet."""
        return self.cursor.toggles_hidden - self._hidden_before

    def _record(self, samples: DecodedSamples, counted: bool) -> None:
        if self.recorder is not None and len(samples):
            self.recorder.samples(samples, counted)

    def _stale(self, samples: DecodedSamples) -> None:
        self.clock.stale(len(samples))
        self._record(samples, counted=False)

    # --- in order --------------------------------------------------------------------------------
    def next(self, n: int) -> DecodedSamples:
        """Up to n samples (pending leftovers first, else exactly n from the stream)."""
        if self.guard is not None:
            self.guard()
        if self._pending is not None and len(self._pending):
            take = self._pending.slice(0, n)
            rest = self._pending.slice(n)
            self._pending = rest if len(rest) else None
        else:
            take = self.cursor.read(n).samples
        # what is consumed once a setpoint has taken effect is counted as plant time (skip, windows)
        self._record(take, counted=self.clock.consume(int(take.index[0])) if len(take) else self.clock.counting)
        return take

    def next_exact(self, n: int) -> DecodedSamples:
        """Exactly the next n samples (pending leftovers first, then the stream)."""
        parts, have = [], 0
        while have < n:
            part = self.next(n - have)
            parts.append(part)
            have += len(part)
        return DecodedSamples.concat(parts)

    def next_index(self) -> int:
        """Index of the next sample this stream hands out."""
        if self._pending is not None and len(self._pending):
            return int(self._pending.index[0])
        return self.cursor.last_index + 1

    def push_back(self, s: DecodedSamples) -> None:
        self._pending = s if self._pending is None else DecodedSamples.concat([s, self._pending])

    def drop_pending_as_stale(self) -> None:
        """Samples read ahead predate every write made since: stale."""
        if self._pending is not None:
            self._stale(self._pending)
            self._pending = None

    def discard_buffered(self) -> None:
        """Without the sync line nothing marks a setpoint's sample: drop what the reader and the port hold."""
        self._pending = None
        self.accounting.doubt("DAQ flushed without the sync line")
        self.clock.stale(self.cursor.discard_buffered())

    def skip(self, seconds: float) -> int:
        """Let `seconds` of plant time pass (DAQ clock: a gap counts as the time it was), counted on the
        clock. Returns the index of the last sample consumed."""
        first = None
        last = None
        n = self.clock.samples_for(seconds)
        while n > 0:
            got = self.next(min(n, 4096))
            first = int(got.index[0]) if first is None else first
            last = int(got.index[-1])
            self.clock.count_until(last)
            n = self.clock.samples_for(seconds) - (last - first + 1)
        return last if last is not None else self.cursor.last_index

    # --- setpoints ---------------------------------------------------------------------------------
    def wait_for_effect(self, max_plant_s: float = 10.0) -> int:
        """Consume the stream up to the sample at which the last setpoint written took effect (its
        sync toggle). Returns that sample's index; what precedes it is stale. `max_plant_s` bounds the
        wait on the DAQ clock (it must cover what the DAQ path holds plus the drive's reaction).

        Across a gap only the level is seen, so toggles go missing in pairs: once the line has then
        been quiet (no toggle, no gap) for the accounting's quiet window, nothing is pending and the
        missing ones are counted as hidden in the gaps (an odd number is an accounting error)."""
        self.drop_pending_as_stale()
        if self.accounting.pending() == 0:
            # nothing written since the last effect (e.g. a move that changed nothing the drive applies)
            self.clock.start_segment_at_next()
            return self.next_index()
        budget = self.clock.samples_for(max_plant_s)
        first_index = None
        gaps = 0
        last_event: int | None = None  # index of the last gap or toggle, once a gap was seen
        while True:
            before = self.cursor.toggles_seen
            chunk = self.cursor.read_available(self.CHUNK_SAMPLES)
            index = chunk.samples.index
            first_index = int(index[0]) if first_index is None else first_index
            missing = self.accounting.pending() + (self.cursor.toggles_seen - before)
            if missing <= 0:
                self.accounting.doubt("more sync toggles seen than setpoints written")
                raise MeasurementError(
                    "sync accounting error: more sync toggles seen than setpoints written "
                    "(the count is established again before the next point)"
                )
            if len(chunk.toggle_offsets) >= missing:
                return self._effect_at(chunk, int(chunk.toggle_offsets[missing - 1]))
            gaps += len(chunk.gap_offsets)
            if gaps:
                events = np.union1d(chunk.gap_offsets, chunk.toggle_offsets)
                if len(events):
                    last_event = int(index[int(events[-1])])
                elif last_event is None:
                    last_event = int(index[0])
                if int(index[-1]) - last_event >= self.accounting.quiet_samples():
                    return self._effect_hidden_in_gaps(chunk, gaps)
            self._stale(chunk.samples)
            if int(index[-1]) - first_index > budget:
                hidden = (
                    (
                        f"; the stream had {gaps} DAQ gap or bad frame(s) meanwhile, which can hide toggles, "
                        "and the line was never quiet after them"
                    )
                    if gaps
                    else ""
                )
                self.accounting.doubt("a setpoint was not confirmed")
                raise MeasurementError(
                    f"setpoint not confirmed on the DAQ sync line within {max_plant_s:g} s of plant time "
                    f"(DAQ sample clock; {self.accounting.pending()} toggle(s) missing{hidden})"
                )

    def _effect_hidden_in_gaps(self, chunk: Chunk, gaps: int) -> int:
        """The line has been quiet since the last gap: the drive has nothing pending, so what is missing
        toggled inside the gaps, in pairs (a pair across a gap shows as no change). The effect is at
        the chunk's last sample at the latest."""
        missing = self.accounting.pending()
        if missing % 2:
            self.accounting.doubt("an odd number of toggles missing after a DAQ gap")
            raise MeasurementError(
                f"sync accounting error after a DAQ gap: {missing} toggle(s) missing, an odd "
                "number, with the line quiet"
            )
        self.cursor.count_hidden_toggles(missing)
        log.warning("%d sync toggle(s) lost in %d DAQ gap(s); setpoint effect taken after the gap", missing, gaps)
        return self._effect_at(chunk, len(chunk.samples) - 1)

    def _effect_at(self, chunk: Chunk, offset: int) -> int:
        """The setpoint took effect at chunk sample `offset`: what precedes it is stale."""
        self._stale(chunk.samples.slice(0, offset))
        self.push_back(chunk.samples.slice(offset))
        effect = int(chunk.samples.index[offset])
        self.clock.start_segment(effect)
        return effect
