"""Measuring at one operating point on the DAQ sample clock.

`OperatingPointSession` implements the MeasurementSession of the identification methods over a
`PointStream` (service/bench/point_stream.py: the point's DAQ stream in order, each setpoint's
effect, and its `PlantClock`, which counts plant time and stale samples): it applies theta and the
injection mode, settles the operating point by measurement (speed and the h-th phasor steady to the
precision the method needs), and measures windows of whole harmonic periods, discarding any window
that holds a gap, a bad frame, a fault flag or another setpoint change.

A `recorder` (service.store.recordings.RunRecorder), while set, receives every sample the session consumes,
marked counted or stale, and each theta setpoint with the sample at which it took effect.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Callable, Literal, overload

import numpy as np

from drivers.daq_protocol import (
    FLAG_OVER_RANGE,
    FLAG_SENSOR_FAULT,
    FLAG_SYNC_INPUT,
    DecodedSamples,
)
from service.bench.contracts import DriveCommands, Recorder
from service.bench.plant_clock import PlantClock
from service.bench.point_stream import PointStream
from service.bench.setpoint_accounting import DaqCursor
from service.identification.session import MeasurementError, Window
from service.model.demodulation import HarmonicFit, ResonanceMode, ResonanceTracker, fit_harmonic
from service.model.harmonic import mechanical_speed_rpm, whole_period_samples

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
MAX_WINDOW_GROWTH = 4.0  # a window extended for precision grows at most this much before its noise is judged again
SPEED_TOLERANCE = 0.005
SETTLE_NOISE_SIGMAS = 3.0
MIN_SETTLE_PRECISION = 0.002  # 0.2 % of |a|: finer than this is below what any window resolves
# A phasor that keeps moving at speed may be beating with a line next to the harmonic (e.g. a high
# order aliased by the sampling): after this many blocks judged without settling, the blocks double
# (up to SETTLE_BLOCK_MAX_FACTOR x): a beat averages out in longer blocks, a drift shows more in them.
SETTLE_BLOCKS_BEFORE_LONGER = 8
SETTLE_BLOCK_MAX_FACTOR = 16


def settle_precision(target_db: float) -> float:
    """Relative phasor drift a method can live with: half its target residual (at 40 dB, 0.5 % of
    |a|): the plant moving by that during the measurement costs at most a few dB of the target."""
    return max(MIN_SETTLE_PRECISION, 0.5 * float(10.0 ** (-target_db / 20.0)))


class RunCancelled(RuntimeError):
    """The operator cancelled the run; raised at the next DAQ read."""


@dataclass(frozen=True)
class Settled:
    """How an operating point settled (DAQ clock)."""

    plant_s: float  # from the move's effect to the end of the last block judged
    speed_rpm: float
    blocks: int
    phasor_change: float  # relative change of the h-th phasor between the last two pairs of blocks


@dataclass(frozen=True)
class SessionSettings:
    """What a session measures at and how (from the run and the bench's settings)."""

    harmonic_order: int
    pole_pairs: int
    sync_input: bool = True  # the DAQ sees the drive's sync line (else settle on the data)
    no_sync_settle_s: float = 0.4  # without it: plant time let pass after a setpoint
    settle_after_theta_s: float = 0.02  # plant time apply_theta lets pass after the setpoint took effect


class OperatingPointSession:
    """MeasurementSession over the real wires (drive over CANopen, alpha over the DAQ).

    Collaborators: the point's `stream` (its DAQ samples in order; its `clock` counts plant time),
    the `commands` it may send (DriveCommands), its `settings`, the bench's shaft mode `resonance`
    (learned across runs; a session of its own starts from the paper's pole), and two one-way
    listeners: `observe(**values)`, what the run sees, for the live status, and `on_window(window)`,
    each accepted window, for progress (CLI, SSE job.progress)."""

    MAX_WINDOW_ATTEMPTS = 5

    def __init__(
        self,
        stream: PointStream,
        commands: DriveCommands,
        settings: SessionSettings,
        resonance: ResonanceTracker | None = None,
        *,
        observe: Callable[..., None] | None = None,
        on_window: Callable[[Window], None] | None = None,
    ):
        self.stream = stream
        self.commands = commands
        self.settings = settings
        self.resonance = resonance or ResonanceTracker(ResonanceMode(-19.6, 6746.2))
        self.harmonic_order = settings.harmonic_order
        self.sample_rate_hz = stream.sample_rate_hz
        self.settle_after_theta_s = settings.settle_after_theta_s  # a validation sets its own
        # the other orders the drive injects beside the session's own (a run of several orders sets them): fitted
        # beside it in every window, as order_window fits them beside each other
        self.also_orders: tuple[int, ...] = ()
        self._observe = observe
        self.on_window = on_window
        self.theta_in_force: tuple[float, float] | None = None  # (cos, sin) the drive applies now in manual mode
        # the further orders in force with it ((order, cos, sin), ...; None: unknown)
        self.further_in_force: tuple[tuple[int, float, float], ...] | None = ()
        self.noise_rms_fs: float | None = None  # rms of alpha around the fitted model, last window
        self.settled: Settled | None = None
        self.over_range_windows = 0  # windows refused: clipped over most of their samples
        self.windows_discarded = 0
        self.speed_rpm_measured: float | None = None

    # --- the stream's bookkeeping, as the methods and the run read it ---------------------------
    @property
    def cursor(self) -> DaqCursor:
        return self.stream.cursor

    @property
    def clock(self) -> PlantClock:
        return self.stream.clock

    @property
    def recorder(self) -> Recorder | None:
        return self.stream.recorder

    @recorder.setter
    def recorder(self, recorder: Recorder | None) -> None:
        self.stream.recorder = recorder

    @property
    def stale_samples(self) -> int:
        return self.clock.stale_samples

    @property
    def plant_time_s(self) -> float:
        return self.clock.plant_time_s

    @property
    def op_settle_plant_s(self) -> float | None:
        return None if self.settled is None else self.settled.plant_s

    def reset_plant_time(self) -> None:
        self.clock.reset_plant_time()

    # --- MeasurementSession ----------------------------------------------------------------------
    def wait_for_effect(self, max_plant_s: float = 10.0) -> int:
        if not self.settings.sync_input:
            return self._settle_on_data(max_plant_s)
        return self.stream.wait_for_effect(max_plant_s)

    def apply_theta(
        self, theta_cos_rad: float, theta_sin_rad: float, further: tuple[tuple[int, float, float], ...] = ()
    ) -> None:
        """theta of the session's order, and of the further orders `further` ((order, cos, sin), applied by the
        same commit); returns once in effect and settled."""
        theta = (float(theta_cos_rad), float(theta_sin_rad))
        further = tuple((int(h), float(c), float(s)) for h, c, s in further)
        if theta == self.theta_in_force and further == self.further_in_force:
            # already in force and settled (the move left it so): nothing to send, wait for or settle
            self.clock.start_segment_at_next()
            if self.recorder is not None:
                self.recorder.setpoint(self.stream.next_index(), *theta)
            return
        self.commands.send_theta(*theta, further)
        effect_index = self.wait_for_effect()
        self.theta_in_force = theta
        self.further_in_force = further
        if self.recorder is not None:
            self.recorder.setpoint(effect_index, *theta)
        self.stream.skip(self.settle_after_theta_s)

    def apply_injection_mode(self, mode: str) -> None:
        """Switch the drive's injection mode (0x2000:2: off / manual / lut; one setpoint, one sync toggle)
        and return once it is in effect and the plant has settled, as apply_theta does."""
        self.commands.send_injection_mode(mode)
        self.theta_in_force = None if mode != "manual" else self.theta_in_force
        self.further_in_force = None if mode != "manual" else self.further_in_force
        self.wait_for_effect()
        self.stream.skip(self.settle_after_theta_s)

    def measure(self, periods: int, max_noise_std_fs: float | None = None, max_periods: int | None = None) -> Window:
        """The next valid window of `periods` whole harmonic periods, demodulated with the shaft mode as
        a nuisance (service.model.demodulation). With `max_noise_std_fs`, the window is extended (same theta,
        contiguous samples) until its phasor's noise is at most that, or it spans `max_periods`."""
        periods = max(periods, min(self._periods_to_resolve_the_shaft(), max_periods or periods))
        samples = self._valid_window(periods)
        fit = self._fit(samples, periods)
        limit = max(max_periods or periods, periods)
        while max_noise_std_fs is not None and fit.noise_std_fs > max_noise_std_fs and periods < limit:
            # noise std falls as 1/sqrt(N): ask for what that predicts, in whole turns, 20 % to spare, but at most
            # MAX_WINDOW_GROWTH times the window before judging its noise again: a window of a few turns has too few
            # bins between the orders for the noise density and falls back to the residual's whole rms, unfitted
            # orders included (service.model.demodulation), which predicted ~1 s where 0.2 s held (500 rpm, the 12th)
            want = periods * min((fit.noise_std_fs / max_noise_std_fs) ** 2 * 1.2, MAX_WINDOW_GROWTH)
            more = min(limit, self.harmonic_order * math.ceil(want / self.harmonic_order)) - periods
            if more <= 0:
                break
            extension = self._valid_window(more, contiguous=True)
            if extension is None:
                break
            samples = DecodedSamples.concat([samples, extension])
            periods += more
            fit = self._fit(samples, periods)
        self._publish(
            speed_rpm=mechanical_speed_rpm(samples.angle_rad, self.sample_rate_hz, self.settings.pole_pairs),
            harmonic_amplitude_fs=fit.phasor.amplitude,
            plant_time_s=self.plant_time_s,
        )
        window = Window(
            fit.phasor,
            samples.accel_fs[: fit.phasor.samples],
            samples.angle_rad[: fit.phasor.samples],
            self.plant_time_s,
            fit.noise_std_fs,
            fit.ring_fs,
        )
        if self.on_window is not None:
            self.on_window(window)
        return window

    def order_window(self, window: Window, order: int, also: tuple[int, ...] = ()) -> Window:
        """The same samples as a window of order `order` (whole electrical turns: every order is whole in them),
        demodulated as the window's own order is, with the shaft mode as a nuisance (a further order near the
        resonance reads the ring of every step otherwise) and the orders `also` fitted beside it (an uncompensated
        6th left in the residual fills the 12th's noise bins), and with its own noise: the residual's density about
        f_order (service.model.demodulation), which is what acts on its phasor. Near the drive's voltage limit the
        lines about the 6th are not those about the 12th (seed 3, 100 ms windows, the phasor's scatter over 40 of
        them against the estimate: 2 Nm / 2600 rpm 3.8e-5 / 3.7e-5 fs at the 6th, 6.7e-5 / 7.3e-5 at the 12th)."""
        turns = max(1, window.phasor.periods // self.harmonic_order)
        fit = fit_harmonic(
            window.alpha_fs,
            window.angle_rad,
            self.sample_rate_hz,
            order,
            turns * order,
            self.resonance.mode,
            also_orders=also,
        )
        return replace(window, phasor=fit.phasor, noise_std_fs=fit.noise_std_fs, ring_fs=fit.ring_fs)

    def _publish(self, **values: object) -> None:
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
        fit = self.resonance.fit(
            samples.accel_fs[:n],
            samples.angle_rad[:n],
            self.sample_rate_hz,
            self.harmonic_order,
            periods,
            usable=~clipped if clipped.any() else None,
            also_orders=self.also_orders,
        )
        self.noise_rms_fs = fit.residual_rms_fs
        return fit

    @overload
    def _valid_window(self, periods: int, contiguous: Literal[False] = False) -> DecodedSamples: ...

    @overload
    def _valid_window(self, periods: int, contiguous: Literal[True]) -> DecodedSamples | None: ...

    def _valid_window(self, periods: int, contiguous: bool = False) -> DecodedSamples | None:
        """Samples spanning `periods` harmonic periods (a little more, cut by the fit) with no gap, bad
        frame, fault flag or setpoint change; a bad one is discarded and measured again. With
        `contiguous`, a bad continuation returns None (the caller keeps what it has)."""
        reasons = {
            "DAQ gap or bad frame": 0,
            "sensor over-range": 0,
            "sensor fault": 0,
            "setpoint change inside the window": 0,
        }
        for _ in range(self.MAX_WINDOW_ATTEMPTS):
            n = self._samples_for(periods)
            s = self.stream.next_exact(n)
            self.clock.count_until(int(s.index[-1]))
            sync = (s.flags & FLAG_SYNC_INPUT) != 0
            setpoint_changed = (sync[1:] != sync[:-1]) if self.settings.sync_input else np.zeros(len(s) - 1, bool)
            bad = np.flatnonzero(s.gap_before[1:] | ((s.flags & BAD_FLAGS) != 0)[1:] | setpoint_changed)
            # over range is not a fault: the clipped samples are left out of the fit (_fit), as long as
            # enough of the window is in range; more than that and too little of the signal is seen
            clipped_fraction = float(np.mean((s.flags & FLAG_OVER_RANGE) != 0))
            if (
                (s.flags[0] & FLAG_SENSOR_FAULT)
                or len(bad)
                or clipped_fraction > MAX_CLIPPED_FRACTION
                or (contiguous and s.gap_before[0])
            ):
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
        raise MeasurementError(
            f"{self.MAX_WINDOW_ATTEMPTS} consecutive windows were invalid: {why}",
            over_range=reasons["sensor over-range"] > 0,
        )

    def _samples_for(self, periods: int) -> int:
        return int(math.ceil(periods * self.sample_rate_hz / self.harmonic_frequency_hz * 1.02)) + 8

    @property
    def harmonic_frequency_hz(self) -> float:
        """f_h = h * f_e at the measured speed."""
        speed = self.speed_rpm_measured
        if not speed:
            raise MeasurementError("speed unknown: settle the operating point first")
        return abs(speed) / 60.0 * self.settings.pole_pairs * self.harmonic_order

    # --- operating-point settling ----------------------------------------------------------------
    def _settle_on_data(self, max_plant_s: float) -> int:
        """A bench without the sync line: drop what is buffered, let `no_sync_settle_s` of plant time
        pass (it must exceed what the DAQ path can still hold, and the plant's settling), then wait
        until two consecutive one-turn phasors agree. Returns the first sample counted as the
        setpoint's time (the first sample read after the write: honest, if pessimistic)."""
        self.stream.discard_buffered()
        self.clock.start_segment_at_next()
        first = self.stream.next(1)
        start = int(first.index[0])
        self.clock.count_until(start)
        self.stream.skip(self.settings.no_sync_settle_s)
        periods = self.harmonic_order  # one electrical turn
        previous = self.measure(periods)
        deadline = start + self.clock.samples_for(max_plant_s)
        while self.cursor.last_index <= deadline:
            current = self.measure(periods)
            # agree within 5 % or within 3 standard deviations of a phasor of noise (std(alpha) sqrt(2/N))
            noise = float(np.std(current.alpha_fs)) * math.sqrt(2.0 / len(current.alpha_fs))
            if abs(current.phasor.complex - previous.phasor.complex) <= 0.05 * abs(current.phasor.complex) + 3 * noise:
                return start
            previous = current
        raise MeasurementError(f"the harmonic did not settle within {max_plant_s:g} s of plant time (no sync line)")

    def _block_speed_rpm(self, s: DecodedSamples) -> float | None:
        try:  # over the block's contiguous runs: a DAQ gap is no change of speed
            return mechanical_speed_rpm(s.angle_rad, self.sample_rate_hz, self.settings.pole_pairs, s.gap_before)
        except ValueError:
            return None  # nothing contiguous to judge: neither steady nor not

    def settle_operating_point(
        self, target_speed_rpm: float, target_db: float = 40.0, max_plant_s: float = 20.0
    ) -> Settled:
        """After the move's setpoints: wait for their effect, then judge blocks of whole electrical
        turns (>= SETTLE_BLOCK_MIN_S) until the encoder speed is within SPEED_TOLERANCE of the target in
        the last two blocks and the h-th phasor is steady to the precision the method needs: the mean
        phasor of the last two blocks within settle_precision(target_db) of the mean of the two before,
        or within SETTLE_NOISE_SIGMAS of their noise (a drift below the noise is not seen, and does not
        matter to a window of the same length). No fixed wait: a point that is steady at once costs
        four blocks. A phasor still moving after SETTLE_BLOCKS_BEFORE_LONGER blocks is judged on blocks
        twice as long (up to SETTLE_BLOCK_MAX_FACTOR x): a line beating with the harmonic averages out
        in them, a drift does not. Bounded by max_plant_s on the DAQ clock."""
        on_window, self.on_window = self.on_window, None  # settling blocks are not the method's windows
        try:
            return self._settle(target_speed_rpm, target_db, max_plant_s)
        finally:
            self.on_window = on_window

    def _settle(self, target_speed_rpm: float, target_db: float, max_plant_s: float) -> Settled:
        if self.settings.sync_input:
            effect = self.stream.wait_for_effect(max_plant_s)
        else:
            # nothing marks the move's sample: drop what is buffered and let no_sync_settle_s pass
            self.stream.discard_buffered()
            effect = int(self.stream.next(1).index[0])
            self.stream.skip(self.settings.no_sync_settle_s)
        self.clock.end_segment()  # the move's time is not the method's
        deadline = effect + self.clock.samples_for(max_plant_s)
        precision = settle_precision(target_db)
        raw_block = self.clock.samples_for(SETTLE_BLOCK_MIN_S)
        speeds: list[float] = []
        phasors: list[complex | None] = []  # None: the block was over range (judged on its speed only)
        noises: list[float] = []

        def forget_blocks() -> None:
            speeds.clear()
            phasors.clear()
            noises.clear()

        gapped = 0
        blocks = 0
        change = math.inf
        block_factor = 1  # SETTLE_BLOCKS_BEFORE_LONGER
        judged_at_factor = 0
        while True:
            if self.speed_rpm_measured is None:
                # the speed first, from raw blocks, so that blocks of whole turns can be cut
                s = self.stream.next_exact(raw_block)
            else:
                turns = block_factor * max(
                    1, math.ceil(SETTLE_BLOCK_MIN_S * self.harmonic_frequency_hz / self.harmonic_order)
                )
                s = self.stream.next_exact(self._samples_for(turns * self.harmonic_order))
            blocks += 1
            sync = (s.flags & FLAG_SYNC_INPUT) != 0
            if (
                s.gap_before[1:].any()
                or (s.flags & FLAG_SENSOR_FAULT).any()
                or (self.settings.sync_input and (sync[1:] != sync[:-1]).any())
            ):
                gapped += 1  # a block with a hole or a fault judges nothing: start again
                forget_blocks()
            else:
                speed = self._block_speed_rpm(s)
                if self.speed_rpm_measured is None:
                    if speed is not None and abs(speed - target_speed_rpm) <= SPEED_TOLERANCE * abs(target_speed_rpm):
                        self.speed_rpm_measured = speed
                elif speed is None:
                    # nothing contiguous to judge (neither steady nor not): the speed is found again from raw blocks
                    self.speed_rpm_measured = None
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
                        except ValueError:  # the speed moved more than the block's margin: judge again
                            forget_blocks()
                            continue
                        phasors.append(fit.phasor.complex)
                        noises.append(fit.noise_std_fs)
                    steady, change = self._steady(target_speed_rpm, speeds, phasors, noises, precision)
                    if steady:
                        settled_speed_rpm = speed
                        break
                    judged_at_factor += 1
                    if judged_at_factor >= SETTLE_BLOCKS_BEFORE_LONGER and block_factor < SETTLE_BLOCK_MAX_FACTOR:
                        block_factor *= 2  # the phasor keeps moving: judge on longer blocks (a beat averages out)
                        judged_at_factor = 0
                        forget_blocks()
            if self.cursor.last_index > deadline:
                last = f"{self.speed_rpm_measured:.1f} rpm" if self.speed_rpm_measured else "speed unknown"
                drift = "" if not math.isfinite(change) else f", h-th phasor still moving {100 * change:.1f} %"
                daq = f"; {gapped} block(s) had DAQ gaps or bad frames" if gapped else ""
                raise MeasurementError(
                    f"the operating point did not settle at {target_speed_rpm:g} rpm within "
                    f"{max_plant_s:g} s of plant time (DAQ sample clock; last {last}{drift}{daq})"
                )
        self.settled = Settled(
            plant_s=(self.cursor.last_index - effect + 1) / self.sample_rate_hz,
            speed_rpm=settled_speed_rpm,
            blocks=blocks,
            phasor_change=change,
        )
        self._publish(speed_rpm=self.speed_rpm_measured)
        return self.settled

    @staticmethod
    def _steady(
        target_speed_rpm: float,
        speeds: list[float],
        phasors: list[complex | None],
        noises: list[float],
        precision: float,
    ) -> tuple[bool, float]:
        """(steady, relative change of the phasor): the last two blocks at the target speed, and the
        mean phasor of the last two blocks within `precision` of the two before, or within their noise.
        Over range (a harmonic next to the shaft resonance clips the sensor), the speed alone: the
        mean speed of the last two blocks within a tenth of the tolerance of the two before."""
        if len(speeds) < 4:
            return False, math.inf
        tolerance = SPEED_TOLERANCE * abs(target_speed_rpm)
        at_speed = all(abs(v - target_speed_rpm) <= tolerance for v in speeds[-2:])
        judged = [p for p in phasors[-4:] if p is not None]
        if len(judged) < 4:  # a block over range among them
            change = abs((speeds[-1] + speeds[-2]) - (speeds[-3] + speeds[-4])) / 2.0
            return at_speed and change <= 0.1 * tolerance, math.inf
        recent = (judged[-1] + judged[-2]) / 2.0
        before = (judged[-3] + judged[-4]) / 2.0
        change = abs(recent - before) / max(abs(recent), 1e-12)
        # noise of the difference of two two-block means: per component sigma, in magnitude sqrt(2) sigma
        sigma = math.sqrt(sum(n * n for n in noises[-4:]) / 4.0)
        noise = SETTLE_NOISE_SIGMAS * math.sqrt(2.0) * sigma
        return at_speed and abs(recent - before) <= max(precision * abs(recent), noise), change
