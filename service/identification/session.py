"""What an identification method needs from the bench while it runs at one operating point."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from service.errors import BenchFailed
from service.model.harmonic import Phasor


class MeasurementError(BenchFailed, RuntimeError):
    """The bench did not deliver what a measurement needs (settling, valid windows, sync).
    `over_range`: the windows were refused because the sensor was clipped over most of them (a
    method can try a smaller step; the caller can say how near the resonance the harmonic is)."""

    def __init__(self, message: str, over_range: bool = False):
        super().__init__(message)
        self.over_range = over_range


@dataclass
class Window:
    """One accepted measurement window: its phasor and the raw samples (to redraw plots)."""

    phasor: Phasor
    alpha_fs: np.ndarray
    angle_rad: np.ndarray
    end_time_s: float  # plant time at the window's last sample, from the session start
    noise_std_fs: float = 0.0  # standard deviation of each phasor component (noise), full scale
    ring_fs: float = 0.0  # amplitude of the shaft mode fitted as a nuisance, full scale


class MeasurementSession(Protocol):
    harmonic_order: int
    sample_rate_hz: float
    settle_after_theta_s: float  # plant time apply_theta lets pass after the setpoint took effect
    also_orders: tuple[int, ...]  # the other orders injected beside the session's own, fitted beside it in measure

    def apply_theta(
        self, theta_cos_rad: float, theta_sin_rad: float, further: tuple[tuple[int, float, float], ...] = ()
    ) -> None:
        """Send theta to the drive (and the further orders' (order, theta_cos, theta_sin), applied by the same
        commit) and return once it is in effect and the plant has settled."""

    harmonic_frequency_hz: float  # f_h at the operating point, Hz

    def measure(self, periods: int, max_noise_std_fs: float | None = None, max_periods: int | None = None) -> Window:
        """Next valid window of `periods` whole harmonic periods (bad windows are re-measured); with
        `max_noise_std_fs`, extended up to `max_periods` until the phasor's noise std is at most that."""

    def order_window(self, window: Window, order: int, also: tuple[int, ...] = ()) -> Window:
        """The same samples as a window of another order, the orders `also` fitted beside it: its phasor and its
        own noise (windows span whole electrical turns)."""

    @property
    def plant_time_s(self) -> float:
        """Plant time spent so far (DAQ samples / rate, from each setpoint's effect)."""

    @property
    def windows_discarded(self) -> int: ...
