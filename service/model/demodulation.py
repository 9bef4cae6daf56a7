"""Harmonic demodulation that knows the shaft: least squares with the resonance mode as a nuisance.

The phasor of docs/conventions.md (Phasors), a_c = (2/N) sum(alpha cos(h phi)), a_s = (2/N) sum(alpha sin(h phi)) over
whole periods, is the least-squares fit of alpha = a_c cos(h phi) + a_s sin(h phi) + e when e holds
only other integer orders. After a setpoint step it does not: the step rings the shaft's lightly
damped mode of G_Salpha (paper sec. 2.3, poles p = sigma +- j omega_r, tau = -1/sigma = 51 ms on
the paper's bench), and a window right after the step carries

    m(t) = e^{sigma t} (b_c cos(omega_r t) + b_s sin(omega_r t)),

which leaks into the h-th phasor by about 1/(pi |f_h - f_r| T) of its amplitude (T the window
length): at the paper's OP2 (f_h = 1200 Hz, f_r = 1074 Hz) a 2 deg theta step rings at 4 times the
harmonic's own amplitude. Fitting m(t) with the harmonic removes it exactly for any time origin
(a shift of t only recombines b_c, b_s), so a window right after a step is unbiased and needs no
settling time. The fit also carries a constant and the orders 1, h-1, h+1, 2h (orthogonal to order
h over whole turns, but not to m(t)).

The mode must sit at the bench's true frequency to within about 1/(10 T): the nominal G_Salpha of
the settings may be off by the bench's spread (the seeded emulator draws it +-10 %). `ResonanceTracker`
learns it from the windows themselves (variable projection over a common scale k of both pole
parts, which keeps the damping ratio) whenever a window carries a strong ring, and keeps the
estimate for the bench: the shaft does not change between operating points.

Units: alpha in sensor full scale (fs), angles in rad, time in s, frequencies in rad/s unless `_hz`.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.model.harmonic import Phasor

RING_SNR_TO_LEARN = 30.0  # learn the mode only from windows whose ring stands this far above its noise
SEARCH_SCALE = 0.15  # every search: +-15 % around the estimate so far (covers a +-10 % bench spread)
LEARNED_STD_HZ = 0.3  # the mode is known once its frequency's standard deviation is below this
LEARN_SAMPLES_MAX = 2400  # samples of a window the search uses: 150 ms at 16 kHz, three tau of the paper's mode


@dataclass(frozen=True)
class ResonanceMode:
    """The shaft mode of G_Salpha: pole sigma + j omega_r (rad/s), sigma < 0 < omega_r."""

    sigma_rad_s: float
    omega_rad_s: float

    @property
    def frequency_hz(self) -> float:
        return self.omega_rad_s / (2.0 * math.pi)

    def scaled(self, k: float) -> "ResonanceMode":
        return ResonanceMode(self.sigma_rad_s * k, self.omega_rad_s * k)


@dataclass(frozen=True)
class HarmonicFit:
    phasor: Phasor
    noise_std_fs: float  # standard deviation of each phasor component from the LS residual, fs
    residual_rms_fs: float  # rms of alpha minus the whole fitted model, fs
    ring_fs: float  # amplitude of the fitted mode at the window start, fs (0 without a mode)
    ring_std_fs: float  # its standard deviation, fs


MAX_ORDERS_NEAR_RESONANCE = 16


def nuisance_orders(harmonic_order: int, electrical_hz: float, mode: ResonanceMode | None) -> list[int]:
    """Integer orders the fit carries besides h: 1, h-1, h+1, 2h, and those the shaft mode amplifies
    (within +-20 % of its frequency), so that a stationary tone there is never taken for the ring."""
    h = harmonic_order
    orders = {1, h - 1, h + 1, 2 * h}
    if mode is not None and electrical_hz > 0:
        low, high = 0.8 * mode.frequency_hz / electrical_hz, 1.2 * mode.frequency_hz / electrical_hz
        near = [k for k in range(max(1, math.ceil(low)), math.floor(high) + 1)]
        orders |= set(near[:MAX_ORDERS_NEAR_RESONANCE])
    return sorted(orders - {0, h})


def _design(
    angle_rad: np.ndarray, t_s: np.ndarray, harmonic_order: int, mode: ResonanceMode | None, orders: list[int]
) -> np.ndarray:
    hphi = harmonic_order * angle_rad
    cols = [np.cos(hphi), np.sin(hphi), np.ones_like(angle_rad)]
    for order in orders:
        cols += [np.cos(order * angle_rad), np.sin(order * angle_rad)]
    if mode is not None:
        envelope = np.exp(mode.sigma_rad_s * t_s)
        cols += [envelope * np.cos(mode.omega_rad_s * t_s), envelope * np.sin(mode.omega_rad_s * t_s)]
    return np.column_stack(cols)


def _solve(x: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Coefficients, residual sum of squares and the unscaled covariance (X^T X)^-1."""
    q, r = np.linalg.qr(x)
    coef = np.linalg.solve(r, q.T @ alpha)
    resid = alpha - x @ coef
    r_inv = np.linalg.inv(r)
    return coef, float(resid @ resid), r_inv @ r_inv.T


def fit_harmonic(
    alpha_fs: np.ndarray,
    angle_rad: np.ndarray,
    sample_rate_hz: float,
    harmonic_order: int,
    periods: int,
    mode: ResonanceMode | None = None,
    usable: np.ndarray | None = None,
    also_orders: tuple[int, ...] = (),
) -> HarmonicFit:
    """Phasor of order h over a window of whole periods, with `mode` (if given) as a nuisance, and the orders
    `also_orders` (the other orders a run injects at once) among the nuisance orders: a larger order left in the
    residual leaks into the noise estimate and, by the window's ends cut to the nearest sample, into the phasor.

    The window must span whole periods (callers cut it with harmonic.whole_period_samples); the
    time origin of the mode is the window's first sample. `usable` (bool per sample) leaves samples
    out of the fit: a sensor clipped at its full scale reads wrong there and only there, and least
    squares over the rest is still unbiased (the noise estimate then comes from the residual)."""
    n = len(alpha_fs)
    t_s = np.arange(n) / sample_rate_hz
    turns = periods / harmonic_order
    electrical_hz = turns * sample_rate_hz / n
    others = sorted((set(nuisance_orders(harmonic_order, electrical_hz, mode)) | set(also_orders)) - {harmonic_order})
    x = _design(angle_rad, t_s, harmonic_order, mode, others)
    alpha = np.asarray(alpha_fs, dtype=float)
    if usable is not None and not usable.all():
        x, alpha = x[usable], alpha[usable]
        coef, rss, cov = _solve(x, alpha)
        sigma2 = rss / max(len(alpha) - x.shape[1], 1)
    else:
        coef, rss, cov = _solve(x, alpha)
        sigma2 = _noise_density(alpha - x @ coef, turns, harmonic_order) or rss / max(n - x.shape[1], 1)
    noise_std = math.sqrt(sigma2 * 0.5 * (cov[0, 0] + cov[1, 1]))
    ring = ring_std = 0.0
    if mode is not None:
        ring = math.hypot(coef[-2], coef[-1])
        ring_std = math.sqrt(sigma2 * 0.5 * (cov[-2, -2] + cov[-1, -1]))
    return HarmonicFit(
        Phasor(float(coef[0]), float(coef[1]), n, periods), noise_std, math.sqrt(rss / n), ring, ring_std
    )


def _noise_density(residual: np.ndarray, turns: float, harmonic_order: int) -> float | None:
    """Noise variance per sample as it acts on order h: the residual's power density around f_h
    (half to one and a half times), leaving out the bins of integer orders, which average out
    over whole turns and would overstate the phasor's noise (a drive's spectrum is full of them).
    The median of the bins, not their mean: a stray tone (the shaft mode rung by the load, a
    non-integer order) fills a bin or two and leaks into the phasor only by 1/(pi df T), so it
    must not count as broadband noise; for white noise, |X_k|^2 / N is exponential with mean s^2
    and median s^2 ln 2. The phasor's noise is then s sqrt(2/N). None when the window is too short
    to tell (fewer than 6 bins)."""
    n = len(residual)
    if abs(turns - round(turns)) > 1e-6 or turns < 1:
        return None
    m = int(round(turns))
    spectrum = np.abs(np.fft.rfft(residual)) ** 2 / n
    bins = np.arange(len(spectrum))
    f_bin = harmonic_order * m  # bin of order h
    band = (bins >= 0.5 * f_bin) & (bins <= 1.5 * f_bin)
    distance_to_order = np.abs(bins - m * np.round(bins / m))
    usable = band & (distance_to_order > 1)
    if usable.sum() < 6:
        return None
    return float(np.median(spectrum[usable]) / math.log(2.0))


def _electrical_hz(angle_rad: np.ndarray, sample_rate_hz: float) -> float:
    """Mean electrical frequency over a record of angles (the DAQ's angle wraps at 2 pi)."""
    turns_rad = np.unwrap(angle_rad)
    return abs(float(turns_rad[-1] - turns_rad[0])) / (2 * math.pi) * sample_rate_hz / max(len(angle_rad) - 1, 1)


def best_mode_scale(
    alpha_fs: np.ndarray,
    angle_rad: np.ndarray,
    sample_rate_hz: float,
    harmonic_order: int,
    nominal: ResonanceMode,
    center: float,
    half_width: float,
) -> tuple[float, float]:
    """Variable projection: the scale k of the nominal pole that minimises the LS residual, searched on
    [center - half_width, center + half_width] (coarse grid, then a parabola through the best three).
    Returns (k, precision of k = 1/var(k)): near its minimum rss(k) ~ rss_min + rss'' (k - k_min)^2 / 2,
    and a least-squares parameter then has var(k) = 2 sigma^2 / rss'' with sigma^2 = rss_min / (n - p)."""
    n = min(len(alpha_fs), LEARN_SAMPLES_MAX)  # the ring lives in the first few tau
    t_s = np.arange(n) / sample_rate_hz
    alpha = np.asarray(alpha_fs[:n], dtype=float)
    angle = angle_rad[:n]
    orders = nuisance_orders(harmonic_order, _electrical_hz(angle, sample_rate_hz), nominal.scaled(center))
    # the columns that do not depend on k are projected out once; each k then costs a 2-column fit
    q_fixed, _ = np.linalg.qr(_design(angle, t_s, harmonic_order, None, orders))
    r0 = alpha - q_fixed @ (q_fixed.T @ alpha)

    def rss(k: float) -> float:
        mode = nominal.scaled(k)
        envelope = np.exp(mode.sigma_rad_s * t_s)
        m = np.column_stack([envelope * np.cos(mode.omega_rad_s * t_s), envelope * np.sin(mode.omega_rad_s * t_s)])
        m -= q_fixed @ (q_fixed.T @ m)
        coef, *_ = np.linalg.lstsq(m, r0, rcond=None)
        resid = r0 - m @ coef
        return float(resid @ resid)

    grid = np.linspace(center - half_width, center + half_width, 41)
    values = np.array([rss(k) for k in grid])
    i = int(np.clip(np.argmin(values), 1, len(grid) - 2))
    fine = np.linspace(grid[i - 1], grid[i + 1], 21)
    fine_values = np.array([rss(k) for k in fine])
    j = int(np.clip(np.argmin(fine_values), 1, len(fine) - 2))
    y0, y1, y2 = fine_values[j - 1 : j + 2]
    denom = y0 - 2 * y1 + y2
    offset = 0.5 * (y0 - y2) / denom if denom > 0 else 0.0
    step = fine[1] - fine[0]
    k = float(fine[j] + np.clip(offset, -1, 1) * step)
    sigma2 = rss(k) / max(n - q_fixed.shape[1] - 2, 1)
    curvature = denom / step**2
    return k, (curvature / (2.0 * sigma2) if curvature > 0 and sigma2 > 0 else 0.0)


class ResonanceTracker:
    """The bench's shaft mode: starts at the settings' G_Salpha pole, learned from strongly ringing
    windows (see module doc) and kept for the bench. Thread-safe; shared by every run on one bench."""

    def __init__(self, nominal: ResonanceMode):
        self.nominal = nominal
        self._lock = threading.Lock()
        self._scale = 1.0
        self._precision = 0.0  # sum of the windows' 1/var(k)
        self._learned_from = 0  # windows that contributed

    @property
    def mode(self) -> ResonanceMode:
        with self._lock:
            return self.nominal.scaled(self._scale)

    @property
    def learned(self) -> bool:
        with self._lock:
            return self._learned_from > 0

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            mode = self.nominal.scaled(self._scale)
            std_hz = self._std_hz()
            return {
                "frequency_hz": round(mode.frequency_hz, 2),
                "sigma_rad_s": round(mode.sigma_rad_s, 3),
                "scale_to_settings": round(self._scale, 5),
                "learned_from_windows": self._learned_from,
                "frequency_std_hz": None if std_hz is None else round(std_hz, 3),
            }

    def _std_hz(self) -> float | None:
        if self._precision <= 0:
            return None
        return self.nominal.frequency_hz / math.sqrt(self._precision)

    def fit(
        self,
        alpha_fs: np.ndarray,
        angle_rad: np.ndarray,
        sample_rate_hz: float,
        harmonic_order: int,
        periods: int,
        usable: np.ndarray | None = None,
        also_orders: tuple[int, ...] = (),
    ) -> HarmonicFit:
        """The window's harmonic fit with the current mode, the orders `also_orders` fitted beside (fit_harmonic);
        a strong ring first refines the mode (never from a window with samples left out: the search needs the
        whole record)."""
        result = fit_harmonic(
            alpha_fs, angle_rad, sample_rate_hz, harmonic_order, periods, self.mode, usable, also_orders
        )
        if usable is not None and not usable.all():
            return result
        with self._lock:
            center = self._scale
            learned = self._learned_from > 0
            std_hz = self._std_hz()  # not None once learned (precision > 0)
            known = learned and std_hz is not None and std_hz < LEARNED_STD_HZ
        # until learned, every window is searched (a mode at the wrong frequency hides its own ring);
        # afterwards only a strong ring refines it, until the frequency is known (the shaft does not change)
        if known or (learned and result.ring_fs <= RING_SNR_TO_LEARN * max(result.ring_std_fs, 1e-12)):
            return result
        # always the wide search: a first estimate off by more than a narrow search would lock in
        k, precision = best_mode_scale(
            alpha_fs, angle_rad, sample_rate_hz, harmonic_order, self.nominal, center, SEARCH_SCALE
        )
        if precision <= 0:
            return result
        refit = fit_harmonic(
            alpha_fs,
            angle_rad,
            sample_rate_hz,
            harmonic_order,
            periods,
            self.nominal.scaled(k),
            also_orders=also_orders,
        )
        if refit.ring_fs > RING_SNR_TO_LEARN * max(refit.ring_std_fs, 1e-12):
            with self._lock:
                # each window an estimate with its own precision: the strong rings next to the
                # resonance outweigh the faint ones of low speed
                self._learned_from += 1
                self._precision += precision
                self._scale += (k - self._scale) * precision / self._precision
            return refit
        return result
