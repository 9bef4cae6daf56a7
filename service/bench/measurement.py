"""Measuring at one operating point on the DAQ sample clock.

`PointStream` consumes the DAQ stream of one operating point in order and keeps its clock: the exact
sample at which each setpoint took effect (the drive's sync toggles, service/bench/setpoint_accounting.py),
which samples are stale (buffered before that: on a real bench CAN and DAQ latency, in the emulator
run as fast as it is read its buffered data) and which count as plant time. Every duration is a
difference of DAQ sample indices, so a gap in the stream (frames lost) counts as the plant time it
was, never as less.

`OperatingPointSession` implements the MeasurementSession of the identification methods on top of
it: it applies theta and the injection mode, settles the operating point by measurement (speed and
the h-th phasor steady to the precision the method needs), and measures windows of whole harmonic
periods, discarding any window that holds a gap, a bad frame, a fault flag or another setpoint change.

A `recorder` (service.recordings.RunRecorder), while set, receives every sample the session consumes,
marked counted or stale as above, and each theta setpoint with the sample at which it took effect.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from drivers.daq_protocol import FLAG_OVER_RANGE, FLAG_SENSOR_FAULT, FLAG_SYNC_INPUT, DecodedSamples
from service.model.demodulation import HarmonicFit, ResonanceMode, ResonanceTracker
from service.model.harmonic import mechanical_speed_rpm, whole_period_samples
from service.identification.session import MeasurementError, Window
from service.bench.setpoint_accounting import Chunk, SetpointAccounting

log = logging.getLogger(__name__)

BAD_FLAGS = FLAG_SENSOR_FAULT
# A window clipped over more than this share of its samples is measured again. Least squares over the
# in-range samples stays unbiased while the model holds (tests/unit/test_demodulation.py: a sine at 20x
# full scale, 97 % clipped, is recovered within 1e-3); beyond 90 % a ~1 kHz harmonic at 16 kHz leaves
# ~1.5 samples per period, the zero crossings, and a strong harmonic next to the shaft resonance is
# exactly the case that needs it (the sensor reads the ring in range only near its zero crossings).
MAX_CLIPPED_FRACTION = 0.9

# Settling (OperatingPointSession.settle_operating_point): blocks of whole electrical turns at least
# this long; the speed within SPEED_TOLERANCE of the target in the last two; the mean h-th phasor of
# the last two blocks within the settling precision of the two before (or within their noise).
SETTLE_BLOCK_MIN_S = 0.01
SPEED_TOLERANCE = 0.005
SETTLE_NOISE_SIGMAS = 3.0
MIN_SETTLE_PRECISION = 0.002     # 0.2 % of |a|: finer than this is below what any window resolves


def settle_precision(target_db: float) -> float:
    """Relative phasor drift a method can live with: half its target residual (at 40 dB, 0.5 % of
    |a|): the plant moving by that during the measurement costs at most a few dB of the target."""
    return max(MIN_SETTLE_PRECISION, 0.5 * 10.0 ** (-target_db / 20.0))


class RunCancelled(RuntimeError):
    """The operator cancelled the run; raised at the next DAQ read."""


class PointStream:
    """The DAQ stream of one operating point, in order, on the DAQ sample clock.

    Plant time is counted from the sample at which each setpoint took effect (`wait_for_effect`) to
    the end of the last sample consumed under it (`count_until`); a segment without a new setpoint
    (`start_segment_at_next`) counts from the next sample read. What precedes an effect is stale."""

    CHUNK_SAMPLES = 4096          # the most one read takes while looking for a toggle

    def __init__(self, accounting: SetpointAccounting, sample_rate_hz: float,
                 guard: Callable[[], None] | None = None):
        self.accounting = accounting
        self.cursor = accounting.cursor
        self.sample_rate_hz = sample_rate_hz
        self.guard = guard          # called before every DAQ read; raises to stop the run (cancel, interlock)
        self._pending: DecodedSamples | None = None   # samples read past the point we needed
        self._segment_start: int | None = None
        self._segment_at_next = False
        self._plant_samples = 0
        self.stale_samples = 0
        self._hidden_before = self.cursor.toggles_hidden
        self.recorder = None        # set for the method's duration by identify_at (raw recording)

    @property
    def toggles_hidden(self) -> int:
        """Setpoint toggles of this point that fell into DAQ gaps and were counted once the line was quiet."""
        return self.cursor.toggles_hidden - self._hidden_before

    def samples_for(self, seconds: float) -> int:
        return int(round(seconds * self.sample_rate_hz))

    def _record(self, samples: DecodedSamples, counted: bool) -> None:
        if self.recorder is not None and len(samples):
            self.recorder.samples(samples, counted)

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
        if self._segment_at_next:
            self._segment_start = int(take.index[0])
            self._segment_at_next = False
        # what is consumed once a setpoint has taken effect is counted as plant time (skip, windows)
        self._record(take, counted=self._segment_start is not None)
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
            self.stale_samples += len(self._pending)
            self._record(self._pending, counted=False)
            self._pending = None

    def discard_buffered(self) -> None:
        """Without the sync line nothing marks a setpoint's sample: drop what the reader and the port hold."""
        self._pending = None
        self.accounting.doubt("DAQ flushed without the sync line")
        self.stale_samples += self.cursor.discard_buffered()

    # --- plant time --------------------------------------------------------------------------------
    def count_until(self, end_index: int) -> None:
        if self._segment_start is not None and end_index >= self._segment_start:
            self._plant_samples += end_index - self._segment_start + 1
            self._segment_start = end_index + 1

    def start_segment_at_next(self) -> None:
        """Count plant time from the next sample read (a measurement under the setpoint in force)."""
        self._segment_start = None
        self._segment_at_next = True

    def end_segment(self) -> None:
        self._segment_start = None
        self._segment_at_next = False

    def start_segment(self, index: int) -> None:
        self._segment_start = index
        self._segment_at_next = False

    @property
    def plant_time_s(self) -> float:
        return self._plant_samples / self.sample_rate_hz

    def reset_plant_time(self) -> None:
        self._plant_samples = 0

    def skip(self, seconds: float) -> int:
        """Let `seconds` of plant time pass (DAQ clock: a gap counts as the time it was). Returns the
        index of the last sample consumed."""
        first = None
        last = None
        n = self.samples_for(seconds)
        while n > 0:
            got = self.next(min(n, 4096))
            first = int(got.index[0]) if first is None else first
            last = int(got.index[-1])
            self.count_until(last)
            n = self.samples_for(seconds) - (last - first + 1)
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
            self.start_segment_at_next()
            return self.next_index()
        budget = self.samples_for(max_plant_s)
        first_index = None
        gaps = 0
        last_event: int | None = None     # index of the last gap or toggle, once a gap was seen
        while True:
            before = self.cursor.toggles_seen
            chunk = self.cursor.read_available(self.CHUNK_SAMPLES)
            index = chunk.samples.index
            first_index = int(index[0]) if first_index is None else first_index
            missing = self.accounting.pending() + (self.cursor.toggles_seen - before)
            if missing <= 0:
                self.accounting.doubt("more sync toggles seen than setpoints written")
                raise MeasurementError("sync accounting error: more sync toggles seen than setpoints written "
                                       "(the count is established again before the next point)")
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
            self.stale_samples += len(chunk.samples)
            self._record(chunk.samples, counted=False)
            if int(index[-1]) - first_index > budget:
                hidden = (f"; the stream had {gaps} DAQ gap or bad frame(s) meanwhile, which can hide toggles, "
                          "and the line was never quiet after them") if gaps else ""
                self.accounting.doubt("a setpoint was not confirmed")
                raise MeasurementError(
                    f"setpoint not confirmed on the DAQ sync line within {max_plant_s:g} s of plant time "
                    f"(DAQ sample clock; {self.accounting.pending()} toggle(s) missing{hidden})")

    def _effect_hidden_in_gaps(self, chunk: Chunk, gaps: int) -> int:
        """The line has been quiet since the last gap: the drive has nothing pending, so what is missing
        toggled inside the gaps, in pairs (a pair across a gap shows as no change). The effect is at
        the chunk's last sample at the latest."""
        missing = self.accounting.pending()
        if missing % 2:
            self.accounting.doubt("an odd number of toggles missing after a DAQ gap")
            raise MeasurementError(f"sync accounting error after a DAQ gap: {missing} toggle(s) missing, an odd "
                                   "number, with the line quiet")
        self.cursor.count_hidden_toggles(missing)
        log.warning("%d sync toggle(s) lost in %d DAQ gap(s); setpoint effect taken after the gap", missing, gaps)
        return self._effect_at(chunk, len(chunk.samples) - 1)

    def _effect_at(self, chunk: Chunk, offset: int) -> int:
        """The setpoint took effect at chunk sample `offset`: what precedes it is stale."""
        self.stale_samples += offset
        self._record(chunk.samples.slice(0, offset), counted=False)
        self.push_back(chunk.samples.slice(offset))
        self.start_segment(int(chunk.samples.index[offset]))
        return self._segment_start


class DriveCommands(Protocol):
    """What a session may send to the drive while it measures (the bench checks every value)."""

    def send_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None: ...

    def send_injection_mode(self, mode: str) -> None: ...


@dataclass(frozen=True)
class Settled:
    """How an operating point settled (DAQ clock)."""
    plant_s: float              # from the move's effect to the end of the last block judged
    speed_rpm: float
    blocks: int
    phasor_change: float        # relative change of the h-th phasor between the last two pairs of blocks


class OperatingPointSession:
    """MeasurementSession over the real wires (drive over CANopen, alpha over the DAQ)."""

    MAX_WINDOW_ATTEMPTS = 5

    def __init__(self, stream: PointStream, commands: DriveCommands, harmonic_order: int, pole_pairs: int,
                 sync_input: bool = True, no_sync_settle_s: float = 0.4, resonance: ResonanceTracker | None = None,
                 observe: Callable[..., None] | None = None, on_window: Callable[[Window], None] | None = None,
                 theta_in_force: tuple[float, float] | None = None, settle_after_theta_s: float = 0.02):
        self.stream = stream
        self.commands = commands
        # the bench's shaft mode (learned across runs); a session of its own starts from the paper's pole
        self.resonance = resonance or ResonanceTracker(ResonanceMode(-19.6, 6746.2))
        self.harmonic_order = harmonic_order
        self.sample_rate_hz = stream.sample_rate_hz
        self.pole_pairs = pole_pairs
        self.sync_input = sync_input
        self.no_sync_settle_s = no_sync_settle_s
        self.settle_after_theta_s = settle_after_theta_s
        self._observe = observe     # observe(**values): what the run sees, for the live status (one-way)
        self.on_window = on_window  # each accepted window, for progress (CLI, SSE job.progress)
        self.theta_in_force = theta_in_force   # (cos, sin) the drive applies now in manual mode, if known
        self.noise_rms_fs: float | None = None      # rms of alpha around the fitted model, last window
        self.settled: Settled | None = None
        self.over_range_windows = 0             # windows refused: clipped over most of their samples
        self.windows_discarded = 0
        self.speed_rpm_measured: float | None = None

    # --- the stream's bookkeeping, as the methods and the run read it ---------------------------
    @property
    def cursor(self):
        return self.stream.cursor

    @property
    def recorder(self):
        return self.stream.recorder

    @recorder.setter
    def recorder(self, recorder) -> None:
        self.stream.recorder = recorder

    @property
    def stale_samples(self) -> int:
        return self.stream.stale_samples

    @property
    def plant_time_s(self) -> float:
        return self.stream.plant_time_s

    @property
    def op_settle_plant_s(self) -> float | None:
        return None if self.settled is None else self.settled.plant_s

    def reset_plant_time(self) -> None:
        self.stream.reset_plant_time()

    def skip(self, seconds: float) -> None:
        """Let the plant settle for `seconds` of plant time (counted as the method's time)."""
        self.stream.skip(seconds)

    # --- MeasurementSession ----------------------------------------------------------------------
    def wait_for_effect(self, max_plant_s: float = 10.0) -> int:
        if not self.sync_input:
            return self._settle_on_data(max_plant_s)
        return self.stream.wait_for_effect(max_plant_s)

    def apply_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None:
        theta = (float(theta_cos_rad), float(theta_sin_rad))
        if theta == self.theta_in_force:
            # already in force and settled (the move left it so): nothing to send, wait for or settle
            self.stream.start_segment_at_next()
            if self.recorder is not None:
                self.recorder.setpoint(self.stream.next_index(), *theta)
            return
        self.commands.send_theta(*theta)
        effect_index = self.wait_for_effect()
        self.theta_in_force = theta
        if self.recorder is not None:
            self.recorder.setpoint(effect_index, *theta)
        self.skip(self.settle_after_theta_s)

    def apply_injection_mode(self, mode: str) -> None:
        """Switch the drive's injection mode (0x2000:2: off / manual / lut; one setpoint, one sync toggle)
        and return once it is in effect and the plant has settled, as apply_theta does."""
        self.commands.send_injection_mode(mode)
        self.theta_in_force = None if mode != "manual" else self.theta_in_force
        self.wait_for_effect()
        self.skip(self.settle_after_theta_s)

    def measure(self, periods: int, max_noise_std_fs: float | None = None, max_periods: int | None = None) -> Window:
        """The next valid window of `periods` whole harmonic periods, demodulated with the shaft mode as
        a nuisance (service.demodulation). With `max_noise_std_fs`, the window is extended (same theta,
        contiguous samples) until its phasor's noise is at most that, or it spans `max_periods`."""
        periods = max(periods, min(self._periods_to_resolve_the_shaft(), max_periods or periods))
        samples = self._valid_window(periods)
        fit = self._fit(samples, periods)
        limit = max(max_periods or periods, periods)
        while max_noise_std_fs is not None and fit.noise_std_fs > max_noise_std_fs and periods < limit:
            # noise std falls as 1/sqrt(N): ask for what that predicts, in whole turns, 20 % to spare
            want = periods * (fit.noise_std_fs / max_noise_std_fs) ** 2 * 1.2
            more = min(limit, self.harmonic_order * math.ceil(want / self.harmonic_order)) - periods
            if more <= 0:
                break
            extension = self._valid_window(more, contiguous=True)
            if extension is None:
                break
            samples = DecodedSamples.concat([samples, extension])
            periods += more
            fit = self._fit(samples, periods)
        self._publish(speed_rpm=mechanical_speed_rpm(samples.angle_rad, self.sample_rate_hz, self.pole_pairs),
                      harmonic_amplitude_fs=fit.phasor.amplitude, plant_time_s=self.plant_time_s)
        window = Window(fit.phasor, samples.accel_fs[:fit.phasor.samples], samples.angle_rad[:fit.phasor.samples],
                        self.plant_time_s, fit.noise_std_fs, fit.ring_fs)
        if self.on_window is not None:
            self.on_window(window)
        return window

    def _publish(self, **values) -> None:
        """Tell the observer what the run sees; the live view must never stop a measurement."""
        if self._observe is None:
            return
        try:
            self._observe(**values)
        except Exception:  # noqa: BLE001
            log.debug("run observer failed", exc_info=True)

    def _periods_to_resolve_the_shaft(self, beats: float = 2.0) -> int:
        """Whole turns of a window long enough to tell the shaft mode from the harmonic: `beats`
        cycles of their difference frequency, T >= beats / |f_h - f_r| (closer to the resonance,
        longer windows)."""
        f_h = self.harmonic_frequency_hz
        distance_hz = max(abs(f_h - self.resonance.mode.frequency_hz), 1.0)
        h = self.harmonic_order
        return h * math.ceil(beats * f_h / distance_hz / h)

    def _fit(self, samples: DecodedSamples, periods: int) -> HarmonicFit:
        n = whole_period_samples(samples.angle_rad, self.harmonic_order, periods)
        clipped = (samples.flags[:n] & FLAG_OVER_RANGE) != 0
        fit = self.resonance.fit(samples.accel_fs[:n], samples.angle_rad[:n], self.sample_rate_hz,
                                 self.harmonic_order, periods, usable=~clipped if clipped.any() else None)
        self.noise_rms_fs = fit.residual_rms_fs
        return fit

    def _valid_window(self, periods: int, contiguous: bool = False) -> DecodedSamples | None:
        """Samples spanning `periods` harmonic periods (a little more, cut by the fit) with no gap, bad
        frame, fault flag or setpoint change; a bad one is discarded and measured again. With
        `contiguous`, a bad continuation returns None (the caller keeps what it has)."""
        reasons = {"DAQ gap or bad frame": 0, "sensor over-range": 0, "sensor fault": 0,
                   "setpoint change inside the window": 0}
        for _ in range(self.MAX_WINDOW_ATTEMPTS):
            n = self._samples_for(periods)
            s = self.stream.next_exact(n)
            self.stream.count_until(int(s.index[-1]))
            sync = (s.flags & FLAG_SYNC_INPUT) != 0
            setpoint_changed = (sync[1:] != sync[:-1]) if self.sync_input else np.zeros(len(s) - 1, bool)
            bad = np.flatnonzero(s.gap_before[1:] | ((s.flags & BAD_FLAGS) != 0)[1:] | setpoint_changed)
            # over range is not a fault: the clipped samples are left out of the fit (_fit), as long as
            # enough of the window is in range; more than that and too little of the signal is seen
            clipped_fraction = float(np.mean((s.flags & FLAG_OVER_RANGE) != 0))
            if (s.flags[0] & FLAG_SENSOR_FAULT) or len(bad) or clipped_fraction > MAX_CLIPPED_FRACTION or (
                    contiguous and s.gap_before[0]):
                self.windows_discarded += 1
                reasons["DAQ gap or bad frame"] += int(s.gap_before[1:].any())
                over = int(clipped_fraction > MAX_CLIPPED_FRACTION)
                reasons["sensor over-range"] += over
                self.over_range_windows += over
                reasons["sensor fault"] += int(((s.flags & FLAG_SENSOR_FAULT) != 0).any())
                reasons["setpoint change inside the window"] += int(setpoint_changed.any())
                if contiguous:
                    return None
                continue
            return s
        why = ", ".join(f"{k} in {v}" for k, v in reasons.items() if v)
        raise MeasurementError(f"{self.MAX_WINDOW_ATTEMPTS} consecutive windows were invalid: {why}",
                               over_range=reasons["sensor over-range"] > 0)

    def _samples_for(self, periods: int) -> int:
        return int(math.ceil(periods * self.sample_rate_hz / self.harmonic_frequency_hz * 1.02)) + 8

    @property
    def harmonic_frequency_hz(self) -> float:
        """f_h = h * f_e at the measured speed."""
        speed = self.speed_rpm_measured
        if not speed:
            raise MeasurementError("speed unknown: settle the operating point first")
        return abs(speed) / 60.0 * self.pole_pairs * self.harmonic_order

    # --- operating-point settling ----------------------------------------------------------------
    def _settle_on_data(self, max_plant_s: float) -> int:
        """A bench without the sync line: drop what is buffered, let `no_sync_settle_s` of plant time
        pass (it must exceed what the DAQ path can still hold, and the plant's settling), then wait
        until two consecutive one-turn phasors agree. Returns the first sample counted as the
        setpoint's time (the first sample read after the write: honest, if pessimistic)."""
        self.stream.discard_buffered()
        self.stream.start_segment_at_next()
        first = self.stream.next(1)
        start = int(first.index[0])
        self.stream.count_until(start)
        self.stream.skip(self.no_sync_settle_s)
        periods = self.harmonic_order                       # one electrical turn
        previous = self.measure(periods)
        deadline = start + self.stream.samples_for(max_plant_s)
        while self.cursor.last_index <= deadline:
            current = self.measure(periods)
            # agree within 5 % or within 3 standard deviations of a phasor of noise (std(alpha) sqrt(2/N))
            noise = float(np.std(current.alpha_fs)) * math.sqrt(2.0 / len(current.alpha_fs))
            if abs(current.phasor.complex - previous.phasor.complex) <= 0.05 * abs(current.phasor.complex) + 3 * noise:
                return start
            previous = current
        raise MeasurementError(f"the harmonic did not settle within {max_plant_s:g} s of plant time (no sync line)")

    def _block_speed_rpm(self, s: DecodedSamples) -> float | None:
        try:    # over the block's contiguous runs: a DAQ gap is no change of speed
            return mechanical_speed_rpm(s.angle_rad, self.sample_rate_hz, self.pole_pairs, s.gap_before)
        except ValueError:
            return None     # nothing contiguous to judge: neither steady nor not

    def settle_operating_point(self, target_speed_rpm: float, target_db: float = 40.0,
                               max_plant_s: float = 20.0) -> Settled:
        """After the move's setpoints: wait for their effect, then judge blocks of whole electrical
        turns (>= SETTLE_BLOCK_MIN_S) until the encoder speed is within SPEED_TOLERANCE of the target in
        the last two blocks and the h-th phasor is steady to the precision the method needs: the mean
        phasor of the last two blocks within settle_precision(target_db) of the mean of the two before,
        or within SETTLE_NOISE_SIGMAS of their noise (a drift below the noise is not seen, and does not
        matter to a window of the same length). No fixed wait: a point that is steady at once costs
        four blocks. Bounded by max_plant_s on the DAQ clock."""
        on_window, self.on_window = self.on_window, None     # settling blocks are not the method's windows
        try:
            return self._settle(target_speed_rpm, target_db, max_plant_s)
        finally:
            self.on_window = on_window

    def _settle(self, target_speed_rpm: float, target_db: float, max_plant_s: float) -> Settled:
        if self.sync_input:
            effect = self.stream.wait_for_effect(max_plant_s)
        else:
            # nothing marks the move's sample: drop what is buffered and let no_sync_settle_s pass
            self.stream.discard_buffered()
            effect = int(self.stream.next(1).index[0])
            self.stream.skip(self.no_sync_settle_s)
        self.stream.end_segment()           # the move's time is not the method's
        deadline = effect + self.stream.samples_for(max_plant_s)
        precision = settle_precision(target_db)
        raw_block = self.stream.samples_for(SETTLE_BLOCK_MIN_S)
        speeds: list[float] = []
        phasors: list[complex | None] = []   # None: the block was over range (judged on its speed only)
        noises: list[float] = []
        gapped = 0
        blocks = 0
        change = math.inf
        while True:
            if self.speed_rpm_measured is None:
                # the speed first, from raw blocks, so that blocks of whole turns can be cut
                s = self.stream.next_exact(raw_block)
            else:
                turns = max(1, math.ceil(SETTLE_BLOCK_MIN_S * self.harmonic_frequency_hz / self.harmonic_order))
                s = self.stream.next_exact(self._samples_for(turns * self.harmonic_order))
            blocks += 1
            sync = (s.flags & FLAG_SYNC_INPUT) != 0
            if s.gap_before[1:].any() or (s.flags & FLAG_SENSOR_FAULT).any() or (self.sync_input and (sync[1:] != sync[:-1]).any()):
                gapped += 1                 # a block with a hole or a fault judges nothing: start again
                speeds.clear(), phasors.clear(), noises.clear()
            else:
                speed = self._block_speed_rpm(s)
                if self.speed_rpm_measured is None:
                    if speed is not None and abs(speed - target_speed_rpm) <= SPEED_TOLERANCE * abs(target_speed_rpm):
                        self.speed_rpm_measured = speed
                else:
                    self.speed_rpm_measured = speed
                    speeds.append(speed)
                    clipped = float(np.mean((s.flags & FLAG_OVER_RANGE) != 0))
                    if clipped > MAX_CLIPPED_FRACTION:
                        phasors.append(None)
                        noises.append(0.0)
                    else:
                        try:
                            fit = self._fit(s, turns * self.harmonic_order)
                        except ValueError:      # the speed moved more than the block's margin: judge again
                            speeds.clear(), phasors.clear(), noises.clear()
                            continue
                        phasors.append(fit.phasor.complex)
                        noises.append(fit.noise_std_fs)
                    steady, change = self._steady(target_speed_rpm, speeds, phasors, noises, precision)
                    if steady:
                        break
            if self.cursor.last_index > deadline:
                last = f"{self.speed_rpm_measured:.1f} rpm" if self.speed_rpm_measured else "speed unknown"
                drift = "" if not math.isfinite(change) else f", h-th phasor still moving {100 * change:.1f} %"
                daq = f"; {gapped} block(s) had DAQ gaps or bad frames" if gapped else ""
                raise MeasurementError(f"the operating point did not settle at {target_speed_rpm:g} rpm within "
                                       f"{max_plant_s:g} s of plant time (DAQ sample clock; last {last}{drift}{daq})")
        self.settled = Settled(plant_s=(self.cursor.last_index - effect + 1) / self.sample_rate_hz,
                               speed_rpm=self.speed_rpm_measured, blocks=blocks, phasor_change=change)
        self._publish(speed_rpm=self.speed_rpm_measured)
        return self.settled

    @staticmethod
    def _steady(target_speed_rpm: float, speeds: list[float], phasors: list[complex | None], noises: list[float],
                precision: float) -> tuple[bool, float]:
        """(steady, relative change of the phasor): the last two blocks at the target speed, and the
        mean phasor of the last two blocks within `precision` of the two before, or within their noise.
        Over range (a harmonic next to the shaft resonance clips the sensor), the speed alone: the
        mean speed of the last two blocks within a tenth of the tolerance of the two before."""
        if len(speeds) < 4:
            return False, math.inf
        tolerance = SPEED_TOLERANCE * abs(target_speed_rpm)
        at_speed = all(abs(v - target_speed_rpm) <= tolerance for v in speeds[-2:])
        if any(p is None for p in phasors[-4:]):
            change = abs((speeds[-1] + speeds[-2]) - (speeds[-3] + speeds[-4])) / 2.0
            return at_speed and change <= 0.1 * tolerance, math.inf
        recent = (phasors[-1] + phasors[-2]) / 2.0
        before = (phasors[-3] + phasors[-4]) / 2.0
        change = abs(recent - before) / max(abs(recent), 1e-12)
        # noise of the difference of two two-block means: per component sigma, in magnitude sqrt(2) sigma
        sigma = math.sqrt(sum(n * n for n in noises[-4:]) / 4.0)
        noise = SETTLE_NOISE_SIGMAS * math.sqrt(2.0) * sigma
        return at_speed and abs(recent - before) <= max(precision * abs(recent), noise), change
