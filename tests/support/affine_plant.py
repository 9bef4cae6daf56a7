"""A closed-form plant for unit tests of the identification algorithms (eq. 15):
alpha(phi) = Re{(S (Theta_d + Theta) + R conj(Theta_d + Theta)) exp(j h phi)} + noise, sampled at
constant speed. R = 0 is a scalar complex secondary path (the rotation-form S_ss of docs/conventions.md,
Secondary path); R != 0 is
the general real 2x2 S_ss a machine with L_d != L_q or dead time shows.

It synthesises real sample records so that the phasor demodulation is exercised too; its truth
(S, Theta_d) is known to the test, which checks the algorithms against -Theta_d in closed form."""

from __future__ import annotations

import math

import numpy as np

from service.identification.session import Window
from service.model.harmonic import phasor


class AffinePlantSession:
    def __init__(
        self,
        s_true: complex,
        theta_d: complex,
        harmonic_order: int = 6,
        speed_rpm: float = 2000.0,
        pole_pairs: int = 4,
        sample_rate_hz: float = 16000.0,
        noise_fs: float = 0.0,
        seed: int = 0,
        settle_samples: int = 160,
        r_conj: complex = 0j,
    ):
        self.s_true, self.theta_d, self.r_conj = s_true, theta_d, r_conj
        self.harmonic_order = harmonic_order
        self.sample_rate_hz = sample_rate_hz
        self.omega_e = speed_rpm / 60 * 2 * math.pi * pole_pairs
        self.noise_fs = noise_fs
        self.rng = np.random.default_rng(seed)
        self.settle_samples = settle_samples
        self.settle_after_theta_s = settle_samples / sample_rate_hz
        self.theta = 0j
        self.sample = 0
        self._plant_samples = 0
        self.sent: list[complex] = []

    def apply_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None:
        self.theta = complex(theta_cos_rad, -theta_sin_rad)
        self.sent.append(self.theta)
        self.sample += self.settle_samples
        self._plant_samples += self.settle_samples

    @property
    def harmonic_frequency_hz(self) -> float:
        return self.harmonic_order * self.omega_e / (2 * math.pi)

    def measure(self, periods: int, max_noise_std_fs: float | None = None, max_periods: int | None = None) -> Window:
        if max_noise_std_fs is not None and self.noise_fs > 0:
            # the phasor of N white-noise samples has std noise * sqrt(2 / N) per component
            samples_needed = 2 * (self.noise_fs / max_noise_std_fs) ** 2
            periods_needed = math.ceil(samples_needed * self.harmonic_frequency_hz / self.sample_rate_hz)
            periods = max(periods, min(periods_needed, max_periods or periods))
        n = int(math.ceil(periods * 2 * math.pi / (self.harmonic_order * self.omega_e) * self.sample_rate_hz)) + 4
        k = self.sample + np.arange(n)
        angle = (self.omega_e * k / self.sample_rate_hz) % (2 * math.pi)
        total = self.theta_d + self.theta
        a = self.s_true * total + self.r_conj * total.conjugate()
        alpha = np.real(a * np.exp(1j * self.harmonic_order * angle)) + self.noise_fs * self.rng.standard_normal(n)
        p = phasor(alpha, angle, self.harmonic_order, periods)
        self.sample += p.samples
        self._plant_samples += p.samples
        return Window(
            p,
            alpha[: p.samples],
            angle[: p.samples],
            self._plant_samples / self.sample_rate_hz,
            self.noise_fs * math.sqrt(2.0 / p.samples),
        )

    @property
    def plant_time_s(self) -> float:
        return self._plant_samples / self.sample_rate_hz

    windows_discarded = 0
