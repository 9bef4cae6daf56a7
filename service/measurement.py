"""Measuring at one operating point on the DAQ sample clock.

`DaqCursor` consumes the DAQ stream in order and counts the drive's sync-flag toggles (bit 2, one
per applied setpoint, DESIGN 5). `OperatingPointSession` implements the MeasurementSession of the
identification methods: it knows the exact sample at which each setpoint took effect, settles on
the data, and measures windows of whole harmonic periods, discarding any window that holds a gap,
a bad frame, a fault flag or another setpoint change.

Plant time is counted on the DAQ clock from the sample at which each setpoint took effect to the
end of the last window measured under it; samples that were buffered before a setpoint took effect
are not the method's time (on a real bench they correspond to CAN latency, in the emulator's fast
mode to buffered data) and are reported separately as `stale_samples`.

A `recorder` (service.recordings.RunRecorder), while set, receives every sample the session consumes,
marked counted or stale as above, and each theta setpoint with the sample at which it took effect.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from drivers.daq_protocol import FLAG_OVER_RANGE, FLAG_SENSOR_FAULT, FLAG_SYNC_INPUT, DecodedSamples
from service.demodulation import HarmonicFit, ResonanceMode, ResonanceTracker
from service.harmonic import mechanical_speed_rpm, whole_period_samples
from service.identification.session import MeasurementError, Window

log = logging.getLogger(__name__)

BAD_FLAGS = FLAG_SENSOR_FAULT
# A window clipped over more than this share of its samples is measured again. Least squares over the
# in-range samples stays unbiased while the model holds (tests/unit/test_demodulation.py: a sine at 20x
# full scale, 97 % clipped, is recovered within 1e-3); beyond 90 % a ~1 kHz harmonic at 16 kHz leaves
# ~1.5 samples per period, the zero crossings, and a strong harmonic next to the shaft resonance is
# exactly the case that needs it (the sensor reads the ring in range only near its zero crossings).
MAX_CLIPPED_FRACTION = 0.9


class RunCancelled(RuntimeError):
    """The operator cancelled the run; raised at the next DAQ read."""


@dataclass
class Chunk:
    samples: DecodedSamples
    toggle_offsets: np.ndarray     # offsets within the chunk where the sync level changed
    gap_offsets: np.ndarray        # offsets of samples with lost samples or a bad frame just before them


class DaqCursor:
    """In-order consumer of a DaqReader that counts sync toggles.

    Across a gap (samples lost: the reader fell behind a DAQ that cannot wait) only the level change is
    seen, so the count stays exact in parity but misses toggles in pairs; `count_hidden_toggles` adds
    them once the caller has shown they happened (OperatingPointSession.wait_for_effect)."""

    def __init__(self, reader, read_timeout_s: float):
        self.reader = reader
        self.read_timeout_s = read_timeout_s
        self.toggles_seen = 0
        self.toggles_hidden = 0        # added by count_hidden_toggles: lost in gaps, for the log and the run
        self.last_index = -1
        self._level: int | None = None

    def discard_buffered(self) -> int:
        """Drop what the reader and the port hold (a bench without the sync line); returns the samples dropped."""
        return self.reader.discard_buffered(flush_port=True)

    def read(self, n: int) -> Chunk:
        samples = self.reader.read(n, self.read_timeout_s)
        level = (samples.flags & FLAG_SYNC_INPUT) != 0
        prev = np.empty_like(level)
        prev[1:] = level[:-1]
        prev[0] = level[0] if self._level is None else bool(self._level)
        toggles = np.flatnonzero(level != prev)
        self._level = int(level[-1])
        self.toggles_seen += len(toggles)
        self.last_index = int(samples.index[-1])
        return Chunk(samples, toggles, np.flatnonzero(samples.gap_before))

    def count_hidden_toggles(self, n: int) -> None:
        """n toggles happened inside gaps of the stream (an even number: the parity was seen)."""
        self.toggles_seen += n
        self.toggles_hidden += n


class OperatingPointSession:
    """MeasurementSession over the real wires (drive over CANopen, alpha over the DAQ)."""

    CHUNK_SAMPLES = 256
    MAX_WINDOW_ATTEMPTS = 5

    def __init__(self, cursor: DaqCursor, send_theta: Callable[[float, float], None],
                 setpoints_written: Callable[[], int], harmonic_order: int, sample_rate_hz: float,
                 pole_pairs: int, settle_after_theta_s: float = 0.02, sync_input: bool = True,
                 no_sync_settle_s: float = 0.4, guard: Callable[[], None] | None = None,
                 resonance: ResonanceTracker | None = None, observe: Callable[..., None] | None = None,
                 on_window: Callable[[Window], None] | None = None,
                 send_injection_mode: Callable[[str], None] | None = None,
                 sync_quiet_samples: int = 20480):
        self._send_theta = send_theta                  # theta to the drive (checked against gamma_max there)
        self._send_injection_mode = send_injection_mode   # off / manual / lut (the LUT's validation)
        self._setpoints_written = setpoints_written    # setpoints the drive accepted: one sync toggle each
        # the bench's shaft mode (learned across runs); a session of its own starts from the paper's pole
        self.resonance = resonance or ResonanceTracker(ResonanceMode(-19.6, 6746.2))
        self.noise_rms_fs: float | None = None      # rms of alpha around the fitted model, last window
        self.op_settle_plant_s: float | None = None # plant time the move to the operating point took
        self.over_range_windows = 0             # windows refused: clipped over most of their samples
        self.guard = guard          # called before every DAQ read; raises to stop the run (cancel, interlock)
        self._observe = observe     # observe(**values): what the run sees, for the live status (one-way)
        self.cursor = cursor
        self.harmonic_order = harmonic_order
        self.sample_rate_hz = sample_rate_hz
        self.pole_pairs = pole_pairs
        self.settle_after_theta_s = settle_after_theta_s
        self.sync_input = sync_input
        # after a gap: no toggle and no gap for this long means the drive has no setpoint pending
        self.sync_quiet_samples = sync_quiet_samples
        self.no_sync_settle_s = no_sync_settle_s
        self._pending: DecodedSamples | None = None   # samples read past the point we needed
        self._segment_start: int | None = None
        self._plant_samples = 0
        self.stale_samples = 0
        self.windows_discarded = 0
        self.speed_rpm_measured: float | None = None
        self.on_window = on_window      # each accepted window, for progress (CLI, SSE job.progress)
        self.recorder = None            # set for the method's duration by identify_at (raw recording)

    def _record(self, samples: DecodedSamples, counted: bool) -> None:
        if self.recorder is not None:
            self.recorder.samples(samples, counted)

    # --- the DAQ stream, in order --------------------------------------------------------------
    def _next(self, n: int) -> DecodedSamples:
        if self.guard is not None:
            self.guard()
        if self._pending is not None and len(self._pending):
            take = self._pending.slice(0, n)
            rest = self._pending.slice(n)
            self._pending = rest if len(rest) else None
        else:
            take = self.cursor.read(n).samples
        # what is consumed once a setpoint has taken effect is counted as plant time (skip, _valid_window)
        self._record(take, counted=self._segment_start is not None)
        return take

    def _next_exact(self, n: int) -> DecodedSamples:
        """Exactly the next n samples (pending leftovers first, then the stream)."""
        parts, have = [], 0
        while have < n:
            part = self._next(n - have)
            parts.append(part)
            have += len(part)
        return DecodedSamples.concat(parts)

    def _push_back(self, s: DecodedSamples) -> None:
        self._pending = s if self._pending is None else DecodedSamples.concat([s, self._pending])

    def wait_for_effect(self, max_plant_s: float = 10.0) -> int:
        """Consume the stream up to the sample at which the last expected setpoint took effect.

        Returns that sample's index. Samples before it are stale (buffered before the setpoint). The
        budget must cover what the pty and the reader hold (about 1-2 s of plant time in the
        emulator's fast mode) plus the drive's reaction."""
        if self._pending is not None:
            # pending samples were already seen by the cursor: their toggles are counted; they
            # predate every write made since, so they are stale
            self.stale_samples += len(self._pending)
            self._record(self._pending, counted=False)
            self._pending = None
        if not self.sync_input:
            return self._settle_on_data(max_plant_s)
        budget = int(max_plant_s * self.sample_rate_hz)
        consumed = 0
        gaps = 0
        quiet = 0       # samples since the later of the last gap and the last toggle (once a gap was seen)
        while True:
            before = self.cursor.toggles_seen
            chunk = self.cursor.read(self.CHUNK_SAMPLES)
            missing = self._setpoints_written() - before
            if len(chunk.toggle_offsets) >= missing > 0:
                offset = int(chunk.toggle_offsets[missing - 1])
                return self._effect_at(chunk, offset)
            if missing <= 0:
                raise MeasurementError("sync accounting error: more sync toggles seen than setpoints written")
            gaps += len(chunk.gap_offsets)
            if gaps:
                last_event = max([-1, *chunk.gap_offsets[-1:], *chunk.toggle_offsets[-1:]])
                quiet = len(chunk.samples) - 1 - last_event if last_event >= 0 else quiet + len(chunk.samples)
                missing = self._setpoints_written() - self.cursor.toggles_seen
                if quiet >= self.sync_quiet_samples:
                    # the drive has nothing pending: what is missing toggled inside the gaps, in pairs (the
                    # level across a gap shows one of a pair as nothing). The effect is before this sample.
                    if missing % 2:
                        raise MeasurementError(f"sync accounting error after a DAQ gap: {missing} toggle(s) "
                                               "missing, an odd number, with the line quiet")
                    self.cursor.count_hidden_toggles(missing)
                    log.warning("%d sync toggle(s) lost in %d DAQ gap(s); setpoint effect taken after the gap",
                                missing, gaps)
                    return self._effect_at(chunk, len(chunk.samples) - 1)
            consumed += len(chunk.samples)
            self.stale_samples += len(chunk.samples)
            self._record(chunk.samples, counted=False)
            if consumed > budget:
                hidden = (f"; the stream had {gaps} DAQ gap or bad frame(s) meanwhile, which can hide toggles, "
                          "and the line was never quiet after them") if gaps else ""
                raise MeasurementError(
                    f"setpoint not confirmed on the DAQ sync line within {max_plant_s} s of plant time "
                    f"({self._setpoints_written() - self.cursor.toggles_seen} toggle(s) missing{hidden})")

    def _effect_at(self, chunk: Chunk, offset: int) -> int:
        """The setpoint took effect at chunk sample `offset`: what precedes it is stale."""
        self.stale_samples += offset
        self._record(chunk.samples.slice(0, offset), counted=False)
        self._push_back(chunk.samples.slice(offset))
        self._segment_start = int(chunk.samples.index[offset])
        return self._segment_start

    def _discard_stale(self) -> None:
        """Without the sync line nothing marks a setpoint's sample: drop what the reader and the port hold."""
        self._pending = None
        self.stale_samples += self.cursor.discard_buffered()

    def _settle_on_data(self, max_plant_s: float) -> int:
        """A bench without the sync line: drop what is buffered, let `no_sync_settle_s` of plant time
        pass (it must exceed what the DAQ path can still hold, and the plant's settling), then wait
        until two consecutive one-turn phasors agree. Returns the first sample counted as the
        setpoint's time (the first sample read after the write: honest, if pessimistic)."""
        self._discard_stale()
        first = self.cursor.read(1).samples
        self._segment_start = int(first.index[0])
        self._record(first, counted=True)
        self.skip(self.no_sync_settle_s)
        periods = self.harmonic_order                       # one electrical turn
        previous = self.measure(periods)
        for _ in range(int(max_plant_s * self.sample_rate_hz / max(previous.phasor.samples, 1))):
            current = self.measure(periods)
            # agree within 5 % or within 3 standard deviations of a phasor of noise (std(alpha) sqrt(2/N))
            noise = float(np.std(current.alpha_fs)) * math.sqrt(2.0 / len(current.alpha_fs))
            if abs(current.phasor.complex - previous.phasor.complex) <= 0.05 * abs(current.phasor.complex) + 3 * noise:
                return self._segment_start
            previous = current
        raise MeasurementError(f"the harmonic did not settle within {max_plant_s} s of plant time (no sync line)")

    def skip(self, seconds: float) -> None:
        """Let the plant settle for `seconds` of plant time (counted as the method's time)."""
        n = int(round(seconds * self.sample_rate_hz))
        while n > 0:
            got = self._next(min(n, 4096))
            n -= len(got)
            self._count_until(int(got.index[-1]))

    def _count_until(self, end_index: int) -> None:
        if self._segment_start is not None and end_index >= self._segment_start:
            self._plant_samples += end_index - self._segment_start + 1
            self._segment_start = end_index + 1

    # --- MeasurementSession ----------------------------------------------------------------------
    def apply_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None:
        self._send_theta(theta_cos_rad, theta_sin_rad)
        effect_index = self.wait_for_effect()
        if self.recorder is not None:
            self.recorder.setpoint(effect_index, theta_cos_rad, theta_sin_rad)
        self.skip(self.settle_after_theta_s)

    def apply_injection_mode(self, mode: str) -> None:
        """Switch the drive's injection mode (0x2000:2: off / manual / lut; one setpoint, one sync toggle)
        and return once it is in effect and the plant has settled, as apply_theta does."""
        if self._send_injection_mode is None:
            raise MeasurementError("this session cannot switch the injection mode")
        self._send_injection_mode(mode)
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
            s = self._next_exact(n)
            self._count_until(int(s.index[-1]))
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

    @property
    def plant_time_s(self) -> float:
        return self._plant_samples / self.sample_rate_hz

    def reset_plant_time(self) -> None:
        self._plant_samples = 0

    # --- operating-point settling ----------------------------------------------------------------
    def settle_operating_point(self, target_speed_rpm: float, settle_s: float, tolerance: float = 0.005,
                               max_plant_s: float = 20.0) -> float:
        """After the OP setpoints: wait for their effect, for the speed (from the encoder angle) to
        hold within `tolerance` of the target for 3 consecutive 20 ms blocks, then `settle_s` more.
        Returns the plant time (s) it took."""
        if self.sync_input:
            self.wait_for_effect(max_plant_s)
        else:
            self._discard_stale()
            self.skip(self.no_sync_settle_s)
        block = int(0.02 * self.sample_rate_hz)
        steady, elapsed, gapped = 0, 0, 0
        speed = math.nan
        while steady < 3:
            s = self._next_exact(block)
            elapsed += len(s)
            gapped += int(s.gap_before[1:].any())
            try:    # over the block's contiguous runs: a DAQ gap is no change of speed
                speed = mechanical_speed_rpm(s.angle_rad, self.sample_rate_hz, self.pole_pairs, s.gap_before)
                steady = steady + 1 if abs(speed - target_speed_rpm) <= tolerance * abs(target_speed_rpm) else 0
            except ValueError:
                pass    # nothing contiguous to judge: neither steady nor not
            if elapsed > max_plant_s * self.sample_rate_hz:
                daq = f"; {gapped} of {elapsed // block} blocks had DAQ gaps or bad frames" if gapped else ""
                raise MeasurementError(f"speed did not settle at {target_speed_rpm:g} rpm within {max_plant_s} s "
                                       f"of plant time (last {speed:.1f} rpm{daq})")
        self.speed_rpm_measured = speed
        self._publish(speed_rpm=speed)
        self._segment_start = None
        skip_n = int(settle_s * self.sample_rate_hz)
        while skip_n > 0:
            got = self._next(min(skip_n, 4096))
            skip_n -= len(got)
            elapsed += len(got)
        self.op_settle_plant_s = elapsed / self.sample_rate_hz
        return self.op_settle_plant_s
