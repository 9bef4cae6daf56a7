"""What an identification method needs from the bench while it runs at one operating point."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from service.harmonic import Phasor


@dataclass
class Window:
    """One accepted measurement window: its phasor and the raw samples (to redraw plots)."""
    phasor: Phasor
    alpha_fs: np.ndarray
    angle_rad: np.ndarray
    end_time_s: float          # plant time at the window's last sample, from the session start


class MeasurementSession(Protocol):
    harmonic_order: int
    sample_rate_hz: float
    settle_after_theta_s: float      # plant time apply_theta lets pass after the setpoint took effect

    def apply_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None:
        """Send theta to the drive and return once it is in effect and the plant has settled."""

    def measure(self, periods: int) -> Window:
        """Next valid window of `periods` whole harmonic periods (bad windows are re-measured)."""

    @property
    def plant_time_s(self) -> float:
        """Plant time spent so far (DAQ samples / rate, from each setpoint's effect)."""

    @property
    def windows_discarded(self) -> int: ...
