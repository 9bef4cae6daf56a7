"""A closed-form plant for unit tests of the identification algorithms (eq. 15):
alpha(phi) = Re{(S (Theta_d + Theta) + R conj(Theta_d + Theta)) exp(j h phi)} + noise, sampled at
constant speed. R = 0 is a scalar complex secondary path (the rotation-form S_ss of docs/conventions.md,
Secondary path); R != 0 is
the general real 2x2 S_ss a machine with L_d != L_q or dead time shows.

It synthesises real sample records so that the phasor demodulation is exercised too; its truth
(S, Theta_d) is known to the test, which checks the algorithms against -Theta_d in closed form."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from service.identification.session import Window
from service.model.harmonic import demodulate, phasor


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
        self.also_orders: tuple[int, ...] = ()  # white noise: nothing of another order to fit beside
        self.theta = 0j
        self.sample = 0
        self._plant_samples = 0
        self.sent: list[complex] = []
        self.whole_turns = False  # windows extended for precision stay whole electrical turns

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
            if self.whole_turns:
                periods_needed = self.harmonic_order * math.ceil(periods_needed / self.harmonic_order)
            periods = max(periods, min(periods_needed, max_periods or periods))
        n = int(math.ceil(periods * 2 * math.pi / (self.harmonic_order * self.omega_e) * self.sample_rate_hz)) + 4
        k = self.sample + np.arange(n)
        angle = (self.omega_e * k / self.sample_rate_hz) % (2 * math.pi)
        alpha = self.signal(angle) + self.noise_fs * self.rng.standard_normal(n)
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

    def order_window(self, window: Window, order: int, also: tuple[int, ...] = ()) -> Window:
        """The same samples as a window of `order`: white noise, so the same noise per phasor component."""
        turns = window.phasor.periods // self.harmonic_order
        return replace(window, phasor=demodulate(window.alpha_fs, window.angle_rad, order, turns * order))

    def signal(self, angle: np.ndarray) -> np.ndarray:
        """alpha without noise at the electrical angles `angle`."""
        total = self.theta_d + self.theta
        a = self.s_true * total + self.r_conj * total.conjugate()
        return np.real(a * np.exp(1j * self.harmonic_order * angle))

    @property
    def plant_time_s(self) -> float:
        return self._plant_samples / self.sample_rate_hz

    windows_discarded = 0


class TwoOrderPlantSession(AffinePlantSession):
    """Orders h and 2h with the cross-terms of one rotation by the summed angle (sec. 2.4, eq. 5-6), in the
    phasor convention A = a_c - j a_s, Theta = theta_cos - j theta_sin:
        A_h  = S_h (Theta_dh + Theta_h)   + S_y conj(Theta_h) Theta_2h
        A_2h = S_2h (Theta_d2h + Theta_2h) + S_x Theta_h^2
    (the gamma^2 term of the rotation puts Theta_h^2 on order 2h; the product of both angles feeds order h).
    The further order's theta arrives through apply_theta's `further` as the drive takes it."""

    def __init__(
        self, s_h: complex, theta_dh: complex, s_2h: complex, theta_d2h: complex, s_x: complex, s_y: complex, **kw
    ):
        super().__init__(s_h, theta_dh, **kw)
        self.s_2h, self.theta_d2h, self.s_x, self.s_y = s_2h, theta_d2h, s_x, s_y
        self.theta_2h = 0j
        self.whole_turns = True  # both orders whole in every window

    def apply_theta(self, theta_cos_rad: float, theta_sin_rad: float, further=()) -> None:
        super().apply_theta(theta_cos_rad, theta_sin_rad)
        orders = {h: complex(c, -s) for h, c, s in further}
        assert set(orders) <= {2 * self.harmonic_order}, orders
        self.theta_2h = orders.get(2 * self.harmonic_order, 0j)

    def phasors(self) -> tuple[complex, complex]:
        a_h = self.s_true * (self.theta_d + self.theta) + self.s_y * self.theta.conjugate() * self.theta_2h
        a_2h = self.s_2h * (self.theta_d2h + self.theta_2h) + self.s_x * self.theta**2
        return a_h, a_2h

    def signal(self, angle: np.ndarray) -> np.ndarray:
        a_h, a_2h = self.phasors()
        h = self.harmonic_order
        return np.real(a_h * np.exp(1j * h * angle) + a_2h * np.exp(2j * h * angle))
