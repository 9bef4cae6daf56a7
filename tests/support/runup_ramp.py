"""A synthetic run-up for the order-tracking tests and benchmark: a linear speed ramp whose electrical
angle is integrated exactly, with orders of known amplitude and phase and white sensor noise.

speed n(t) = n0 + (n1 - n0) t / T (rpm); phi_e(t) = N_p 2 pi / 60 (n0 t + (n1 - n0) t^2 / (2 T)). An order h
with amplitude a and phase psi is alpha = a cos(h phi_e + psi) = Re(a e^{j psi} e^{j h phi_e}), i.e. the
phasor A = a e^{j psi} = a_c - j a_s of docs/conventions.md (Phasors).
"""

from __future__ import annotations

import math

import numpy as np

RATE_HZ = 16_000.0
POLE_PAIRS = 4


def ramp_angle(n0_rpm: float, n1_rpm: float, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, unwrapped phi_e) of a linear ramp n0 -> n1 over duration_s, sampled at RATE_HZ."""
    t = np.arange(int(duration_s * RATE_HZ)) / RATE_HZ
    rate = (n1_rpm - n0_rpm) / duration_s
    phi = POLE_PAIRS * 2 * math.pi / 60 * (n0_rpm * t + 0.5 * rate * t**2)
    return t, phi


def tone(phi: np.ndarray, order: int, amplitude: np.ndarray | float, phase_deg: float) -> np.ndarray:
    """Order `order` of the angle with this amplitude (fs) and phase (deg of A)."""
    return np.asarray(amplitude * np.cos(order * phi + math.radians(phase_deg)))


def ramp_record(
    n0_rpm: float,
    n1_rpm: float,
    orders: dict[int, tuple[float, float]],
    noise_fs: float,
    duration_s: float = 16.0,
    seed: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """(wrapped angle as the DAQ gives it, alpha): `orders` {h: (amplitude fs, phase deg)} plus white noise."""
    t, phi = ramp_angle(n0_rpm, n1_rpm, duration_s)
    alpha = np.random.default_rng(seed).normal(0.0, noise_fs, len(t))
    for order, (amplitude, phase_deg) in orders.items():
        alpha += tone(phi, order, amplitude, phase_deg)
    return np.mod(phi, 2 * math.pi), alpha
