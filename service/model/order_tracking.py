"""Computed order tracking of a run-up: each order's phasor per speed bin, as NVH labs judge a speed ramp.

Order h is h times the electrical frequency, and its phasor follows docs/conventions.md (Phasors) and
service/model/harmonic.py exactly: alpha = a_c cos(h phi_e) + a_s sin(h phi_e), A = a_c - j a_s, phase
atan2(-a_s, a_c) wrapped to (-180, 180] deg, amplitudes in sensor full scale (fs).

Method. The record is cut at the DAQ's gaps (`gap_before`) into contiguous runs, each unwrapped on its
own (the angle's step across a gap is unknown, as in harmonic.electrical_frequency_hz), and each run into
consecutive windows of `window_periods` whole electrical periods, cut on the encoder angle itself (the
sample whose advance is nearest to 2 pi k, as harmonic.whole_period_samples): order h then makes exactly
h * window_periods cycles in a window, with no leakage at constant speed. The remainder of a run before a
gap (or at the end) is left out, so no window spans a gap. Each window's mean mechanical speed
(harmonic.mechanical_speed_rpm) decides its bin, centred on a multiple of `bin_width_rpm`; the bins cover
the windows' speeds without a hole (a bin no window fell into reads NaN with 0 windows). The windows of a
bin are averaged as phasors (complex mean), then amplitude and phase; a down-ramp and an up-ramp give the
same bins (call it once per direction to see both).

Each window's phasors come from one least-squares fit of cos(h phi_e), sin(h phi_e) of every order asked
and a constant, at the samples' own angles. The samples are uniform in time, not in angle; the other way,
resampling alpha to a uniform angle grid by interpolation and taking the DFT, was tried on the test's
ramp (16 kHz, 4 pole pairs, 1000-2600 rpm): linear interpolation attenuates an order by about
sinc^2(f_h / f_s), 5 % at order 12 and 2600 rpm (f_h = 2.1 kHz), 40 % at order 40; the fit at the sample
angles is exact for any speed profile within the window (the test holds 2 % and 1 deg per bin). An order
is fitted in a window only while its frequency stays below MAX_FREQUENCY_TO_SAMPLE_RATE of the sample rate
(the DAQ has no anti-alias filter: above that the fit is ill-conditioned and the tone folds); where no
window of a bin could fit it, it reads NaN.

`mode` (optional, service/model/demodulation.py): the shaft's lightly damped mode as a nuisance, the same
decaying ring e^{sigma t} (b_c cos(omega_r t) + b_s sin(omega_r t)) from each window's first sample that
demodulation fits; a ring that started before the window is the same term (a shift of t only recombines
b_c, b_s). A ramp at constant torque has no setpoint step, but its start (the load's acceleration step)
rings the shaft; the mode's frequency comes from the bench's ResonanceTracker. The order's own response
near the resonance (G_Salpha amplifying it) is what a run-up measures, not a nuisance.

Noise floor. Each window's residual (alpha minus the whole fit) is taken to the frequency domain; its
bins between the integer orders (more than one bin away from every multiple of window_periods: the half
orders of a 4-period window) hold only broadband noise, whose per-sample variance is their median power
/ ln 2 (for white noise |X_k|^2 / N is exponential with mean s^2; the median ignores a stray tone, as
demodulation's noise estimate does). An order's phasor in one window has that noise with variance
2 s^2 / N in each component; the bin's complex mean of K windows the mean of theirs over K. The bin's
`noise_floor_fs` is then the rms amplitude sqrt(E|A|^2) an order without any tone shows in that bin
(a Rayleigh amplitude: its mean is 0.886 of that): an order reading several times its bin's noise floor
is above the noise. Unfitted orders that are present (a drive's spectrum is full of them) sit on integer
orders and do not count here; they do leak into the orders asked for, by up to ~1e-3 of their amplitude
per window (the window's ends are cut to the nearest sample, so it spans whole periods only to about
half a sample): ask for every strong order (the run-up's default survey of orders 1..48 does).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.model.demodulation import ResonanceMode
from service.model.harmonic import mechanical_speed_rpm

DEFAULT_BIN_WIDTH_RPM = 10.0
DEFAULT_WINDOW_PERIODS = 4  # electrical periods per window: half orders between the orders for the noise floor
MIN_WINDOW_PERIODS = 4  # fewer leave no bin between the orders' bins (noise floor)
MAX_FREQUENCY_TO_SAMPLE_RATE = 0.4  # an order is fitted while f_h < 0.4 f_s (2.5 samples per cycle)
LN2 = math.log(2.0)


@dataclass(frozen=True)
class OrderTrack:
    """Orders per speed bin (module doc). Arrays: amplitude_fs and phase_deg [order][bin]; the rest [bin]."""

    speed_rpm: np.ndarray  # bin centres, ascending, bin_width_rpm apart
    orders: tuple[int, ...]
    amplitude_fs: np.ndarray  # |complex mean of the windows' phasors|, fs; NaN where not fitted
    phase_deg: np.ndarray  # phase of A = a_c - j a_s, (-180, 180] deg; NaN where not fitted
    noise_floor_fs: np.ndarray  # rms amplitude of an order without a tone in the bin, fs; NaN in an empty bin
    windows: np.ndarray  # windows averaged in each bin (int)
    bin_width_rpm: float

    @property
    def phasor(self) -> np.ndarray:
        """Complex A = a_c - j a_s per [order][bin] (amplitude and phase together)."""
        return np.asarray(self.amplitude_fs * np.exp(1j * np.deg2rad(self.phase_deg)))


@dataclass(frozen=True)
class _Window:
    speed_rpm: float
    phasors: np.ndarray  # complex A per order, NaN where the order was not fitted
    noise_variance_fs2: float  # per-sample variance of the noise between the orders
    samples: int


def contiguous_runs(angle_rad: np.ndarray, gap_before: np.ndarray | None) -> list[tuple[int, np.ndarray]]:
    """(first sample, unwrapped angle) of each run of samples without a DAQ gap inside it."""
    angle = np.asarray(angle_rad, dtype=float)
    cuts = np.flatnonzero(np.asarray(gap_before)[1:]) + 1 if gap_before is not None else np.zeros(0, int)
    starts = np.concatenate([[0], cuts])
    return [(int(start), np.unwrap(run)) for start, run in zip(starts, np.split(angle, cuts), strict=True)]


def window_bounds(unwrapped_rad: np.ndarray, window_periods: int) -> list[tuple[int, int]]:
    """[start, stop) of consecutive windows of `window_periods` whole electrical periods over one run,
    each cut at the sample whose advance from the window's start is nearest to 2 pi window_periods."""
    if len(unwrapped_rad) < 2:
        return []
    direction = 1.0 if unwrapped_rad[-1] >= unwrapped_rad[0] else -1.0
    advance = direction * (unwrapped_rad - unwrapped_rad[0])
    step = 2.0 * math.pi * window_periods
    bounds: list[tuple[int, int]] = []
    start = 0
    while True:
        target = advance[start] + step
        stop = int(np.searchsorted(advance, target))
        if stop >= len(advance):
            return bounds  # the remainder is not a whole window
        if abs(advance[stop - 1] - target) < abs(advance[stop] - target):
            stop -= 1
        if stop <= start:
            return bounds
        bounds.append((start, stop))
        start = stop


def _residual_noise_variance(residual: np.ndarray, window_periods: int) -> float:
    """Per-sample variance of the broadband noise: median power of the bins between the orders / ln 2."""
    n = len(residual)
    power = np.abs(np.fft.rfft(residual)) ** 2 / n
    bins = np.arange(len(power))
    distance_to_order = np.abs(bins - window_periods * np.round(bins / window_periods))
    between = (distance_to_order > 1) & (bins > 0) & (bins < n // 2)
    if not between.any():
        return math.nan
    return float(np.median(power[between]) / LN2)


def _fit_window(
    alpha_fs: np.ndarray,
    angle_rad: np.ndarray,
    orders: np.ndarray,
    sample_rate_hz: float,
    pole_pairs: int,
    window_periods: int,
    mode: ResonanceMode | None,
) -> _Window:
    n = len(alpha_fs)
    speed_rpm = mechanical_speed_rpm(angle_rad, sample_rate_hz, pole_pairs)
    # the fastest the window turns: the order's highest frequency in it
    electrical_hz_max = float(np.max(np.abs(np.diff(angle_rad)))) * sample_rate_hz / (2.0 * math.pi)
    fitted = orders * electrical_hz_max < MAX_FREQUENCY_TO_SAMPLE_RATE * sample_rate_hz
    tones = np.exp(1j * np.outer(angle_rad, orders[fitted]))
    columns = [tones.real, tones.imag, np.ones((n, 1))]
    if mode is not None:
        t_s = np.arange(n) / sample_rate_hz
        envelope = np.exp(mode.sigma_rad_s * t_s)
        columns.append(
            np.column_stack([envelope * np.cos(mode.omega_rad_s * t_s), envelope * np.sin(mode.omega_rad_s * t_s)])
        )
    design = np.hstack(columns)
    # normal equations: the columns are near orthogonal over whole periods (condition ~1), and this is
    # ~100 times faster than an SVD-based lstsq for 48 orders
    coef = np.linalg.solve(design.T @ design, design.T @ alpha_fs)
    k = int(fitted.sum())
    phasors = np.full(len(orders), complex(math.nan, math.nan))
    phasors[fitted] = coef[:k] - 1j * coef[k : 2 * k]  # A = a_c - j a_s
    noise_variance = _residual_noise_variance(alpha_fs - design @ coef, window_periods)
    return _Window(speed_rpm, phasors, noise_variance, n)


def track_orders(
    angle_rad: np.ndarray,
    alpha_fs: np.ndarray,
    sample_rate_hz: float,
    pole_pairs: int,
    orders: Sequence[int],
    bin_width_rpm: float = DEFAULT_BIN_WIDTH_RPM,
    gap_before: np.ndarray | None = None,
    window_periods: int = DEFAULT_WINDOW_PERIODS,
    mode: ResonanceMode | None = None,
) -> OrderTrack:
    """Orders per speed bin of a ramp (module doc).

    angle_rad: the electrical angle per sample, wrapped (the DAQ's [0, 2 pi)) or unwrapped; alpha_fs:
    the acceleration per sample (fs); gap_before: the DAQ decoder's flag (samples lost just before this
    one), None for a record without gaps; mode: the shaft mode as a nuisance (None: none fitted)."""
    angle = np.asarray(angle_rad, dtype=float)
    alpha = np.asarray(alpha_fs, dtype=float)
    if angle.shape != alpha.shape or angle.ndim != 1:
        raise ValueError(f"angle ({angle.shape}) and acceleration ({alpha.shape}) must be 1-d records of one length")
    if not orders or any(int(h) != h or h < 1 for h in orders):
        raise ValueError(f"orders must be positive integers, got {list(orders)!r}")
    if not (math.isfinite(bin_width_rpm) and bin_width_rpm > 0):
        raise ValueError(f"bin width {bin_width_rpm!r} rpm must be positive")
    if window_periods < MIN_WINDOW_PERIODS:
        raise ValueError(
            f"windows of {window_periods} periods leave no bins between the orders (at least {MIN_WINDOW_PERIODS})"
        )
    order_array = np.asarray([int(h) for h in orders], dtype=float)
    windows = [
        _fit_window(
            alpha[first + start : first + stop],
            run[start:stop],
            order_array,
            sample_rate_hz,
            pole_pairs,
            window_periods,
            mode,
        )
        for first, run in contiguous_runs(angle, gap_before)
        for start, stop in window_bounds(run, window_periods)
    ]
    if not windows:
        raise ValueError("the record holds no whole window of contiguous samples")
    return _bin_windows(windows, tuple(int(h) for h in orders), bin_width_rpm)


def _bin_windows(windows: list[_Window], orders: tuple[int, ...], bin_width_rpm: float) -> OrderTrack:
    speeds = np.array([w.speed_rpm for w in windows])
    bin_of_window = np.round(speeds / bin_width_rpm).astype(int)
    first, last = int(bin_of_window.min()), int(bin_of_window.max())
    n_bins = last - first + 1
    index = bin_of_window - first
    phasors = np.array([w.phasors for w in windows]).T  # [order][window]
    fitted = np.isfinite(phasors)
    sums = np.zeros((len(orders), n_bins), dtype=complex)
    counts = np.zeros((len(orders), n_bins))
    for order_row in range(len(orders)):
        np.add.at(sums[order_row], index, np.where(fitted[order_row], phasors[order_row], 0.0))
        np.add.at(counts[order_row], index, fitted[order_row])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / counts, complex(math.nan, math.nan))
    window_count = np.bincount(index, minlength=n_bins)
    # each window's phasor component variance 2 s^2 / N; the mean of K windows: their sum / K^2
    component_variance = np.zeros(n_bins)
    np.add.at(component_variance, index, [2.0 * w.noise_variance_fs2 / w.samples for w in windows])
    with np.errstate(invalid="ignore", divide="ignore"):
        noise_floor = np.where(window_count > 0, np.sqrt(2.0 * component_variance) / window_count, math.nan)
    phase_deg = np.degrees(np.angle(mean))
    phase_deg = np.where(phase_deg <= -180.0, phase_deg + 360.0, phase_deg)  # (-180, 180]
    return OrderTrack(
        speed_rpm=(np.arange(first, last + 1) * bin_width_rpm).astype(float),
        orders=orders,
        amplitude_fs=np.abs(mean),
        phase_deg=phase_deg,
        noise_floor_fs=noise_floor,
        windows=window_count,
        bin_width_rpm=float(bin_width_rpm),
    )


DEFAULT_LIST_ABOVE_DB = 20.0  # an order is listed where it stands this far above its bins' noise floor ...
DEFAULT_LIST_MIN_FRACTION = 0.25  # ... in at least this fraction of the bins where it was fitted


@dataclass(frozen=True)
class ProminentOrder:
    """An order that stands above the noise over the range (`prominent_orders`): what an engineer picks
    the orders to compensate from."""

    order: int
    max_amplitude_fs: float  # the largest bin amplitude over the range, fs
    at_speed_rpm: float  # the bin of that largest amplitude
    median_above_floor_db: float  # median over the fitted bins of 20 log10(amplitude / noise floor)
    fraction_above: float  # of the fitted bins, the fraction at least level_db above the floor

    def public(self) -> dict[str, float | int]:
        return {
            "order": self.order,
            "max_amplitude": self.max_amplitude_fs,
            "at_speed_rpm": self.at_speed_rpm,
            "median_above_floor_db": self.median_above_floor_db,
            "fraction_above": self.fraction_above,
        }


def prominent_orders(
    track: OrderTrack, level_db: float = DEFAULT_LIST_ABOVE_DB, min_fraction: float = DEFAULT_LIST_MIN_FRACTION
) -> list[ProminentOrder]:
    """The orders at least `level_db` above their bin's noise floor in at least `min_fraction` of the bins
    where they were fitted, largest first (a resonance crossing of one bin does not list an order: an order
    to compensate is there over the range). An order fitted in no bin is never listed."""
    listed = []
    for k, order in enumerate(track.orders):
        amplitude = track.amplitude_fs[k]
        fitted = np.isfinite(amplitude) & np.isfinite(track.noise_floor_fs) & (track.noise_floor_fs > 0)
        if not fitted.any():
            continue
        above_db = 20.0 * np.log10(np.maximum(amplitude[fitted], 1e-300) / track.noise_floor_fs[fitted])
        fraction = float(np.mean(above_db >= level_db))
        if fraction < min_fraction:
            continue
        best = int(np.nanargmax(np.where(fitted, amplitude, np.nan)))
        listed.append(
            ProminentOrder(
                order=int(order),
                max_amplitude_fs=float(amplitude[best]),
                at_speed_rpm=float(track.speed_rpm[best]),
                median_above_floor_db=float(np.median(above_db)),
                fraction_above=fraction,
            )
        )
    return sorted(listed, key=lambda p: -p.max_amplitude_fs)
