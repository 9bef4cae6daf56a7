"""Harmonic phasor of the measured acceleration over whole harmonic periods (docs/conventions.md, Phasors).

    a_c = (2/N) sum(alpha * cos(h phi_e)),  a_s = (2/N) sum(alpha * sin(h phi_e))

over a window of N samples spanning an integer number of harmonic periods (a window that is not
an integer number of periods biases the result, so `whole_period_samples` picks N from the
encoder angle itself, not from the nominal speed). Windows of a multiple of h periods span whole
electrical turns, so every other integer order (1st, 2h, ...) averages out too: the defaults of the
methods use such windows. Units: alpha in sensor full scale, phi_e in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Phasor:
    a_c: float
    a_s: float
    samples: int
    periods: int

    @property
    def amplitude(self) -> float:
        return math.hypot(self.a_c, self.a_s)

    def as_dict(self) -> dict[str, float]:
        """The phasor as results and validations keep it (fs)."""
        return {"a_c": self.a_c, "a_s": self.a_s, "amplitude": self.amplitude}

    @property
    def vector(self) -> np.ndarray:
        """[a_c, a_s], the real form that S_ss acts on (docs/conventions.md, Secondary path)."""
        return np.array([self.a_c, self.a_s])

    @property
    def complex(self) -> complex:
        """A = a_c - j a_s (so that A = S (Theta_d + Theta), see secondary_path)."""
        return complex(self.a_c, -self.a_s)


def unwrap_angle(angle_rad: np.ndarray) -> np.ndarray:
    return np.unwrap(angle_rad)


def whole_period_samples(angle_rad: np.ndarray, harmonic_order: int, periods: int) -> int:
    """Number of samples N such that the window [0, N) spans `periods` harmonic periods.

    The harmonic phase h*phi advances 2*pi per period; N is the sample count whose phase advance
    is closest to 2*pi*periods. Raises if the angle record is too short for that many periods.
    """
    phase = harmonic_order * unwrap_angle(angle_rad)
    advance = np.abs(phase - phase[0])
    target = 2.0 * math.pi * periods
    end = int(np.searchsorted(advance, target))
    if end >= len(advance):
        raise ValueError(
            f"record of {len(angle_rad)} samples spans fewer than {periods} periods of order {harmonic_order}"
        )
    # sample `end` has advanced >= target: the window [0, end) ends one step short of the period boundary
    if end > 0 and abs(advance[end - 1] - target) < abs(advance[end] - target):
        end -= 1
    return end


def phasor(alpha_fs: np.ndarray, angle_rad: np.ndarray, harmonic_order: int, periods: int) -> Phasor:
    """Phasor of order h over the first `periods` whole periods of the record."""
    n = whole_period_samples(angle_rad, harmonic_order, periods)
    return demodulate(alpha_fs[:n], angle_rad[:n], harmonic_order, periods)


def demodulate(alpha_fs: np.ndarray, angle_rad: np.ndarray, harmonic_order: int, periods: int) -> Phasor:
    """Phasor of order h over the whole record, which must span `periods` whole periods of it (a window cut
    to whole electrical turns spans whole periods of every integer order)."""
    n = len(alpha_fs)
    hphi = harmonic_order * angle_rad
    a_c = 2.0 / n * float(np.dot(alpha_fs, np.cos(hphi)))
    a_s = 2.0 / n * float(np.dot(alpha_fs, np.sin(hphi)))
    return Phasor(a_c, a_s, n, periods)


def samples_per_period(speed_rpm: float, pole_pairs: int, harmonic_order: int, sample_rate_hz: float) -> float:
    f_h = speed_rpm / 60.0 * pole_pairs * harmonic_order
    return sample_rate_hz / f_h


def amplitude_spectrum(alpha_fs: np.ndarray, angle_rad: np.ndarray, max_order: int) -> list[float]:
    """Amplitudes of electrical orders 1..max_order over the whole electrical periods in the record."""
    phase = unwrap_angle(angle_rad)
    turns = int(abs(phase[-1] - phase[0]) // (2 * math.pi))
    if turns < 1:
        return []
    out = []
    for order in range(1, max_order + 1):
        out.append(phasor(alpha_fs, angle_rad, order, turns * order).amplitude)
    return out


def mechanical_speed_rpm(
    angle_rad: np.ndarray, sample_rate_hz: float, pole_pairs: int, gap_before: np.ndarray | None = None
) -> float:
    """Mechanical speed (rpm) seen by the encoder over a record of electrical angles (see
    electrical_frequency_hz for `gap_before`)."""
    return electrical_frequency_hz(angle_rad, sample_rate_hz, gap_before) * 60.0 / pole_pairs


def electrical_frequency_hz(
    angle_rad: np.ndarray, sample_rate_hz: float, gap_before: np.ndarray | None = None
) -> float:
    """Mean electrical frequency (Hz) over a record of the encoder angle (rad) sampled at sample_rate_hz.

    gap_before[i] (the DAQ decoder's flag) marks samples lost or a bad frame skipped just before
    sample i. The angle's step across a gap is unknown (it may wrap by more than half a turn), so the
    record is taken as its contiguous runs: f_e = fs * sum(advance of each run) / (2 pi * sum(len - 1
    of each run)). Without gaps this is the record's unwrapped advance over its length."""
    angle = np.asarray(angle_rad, dtype=float)
    cuts = np.flatnonzero(np.asarray(gap_before)[1:]) + 1 if gap_before is not None else ()
    turns, intervals = 0.0, 0
    for run in np.split(angle, cuts):
        if len(run) >= 2:
            turns += (np.unwrap(run)[-1] - run[0]) / (2.0 * math.pi)
            intervals += len(run) - 1
    if intervals == 0:
        raise ValueError("need at least two contiguous samples to estimate the speed")
    return float(turns * sample_rate_hz / intervals)
