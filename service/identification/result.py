"""The result of one identification, self-describing enough to store and to redraw its plots."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from service.model.harmonic import Phasor
from service.model.secondary_path import gamma_delta


def suppression_db(uncompensated: Phasor, residual: Phasor) -> float:
    """20 log10(|a_uncompensated| / |a_residual|), dB (positive = harmonic reduced)."""
    return 20.0 * math.log10(max(uncompensated.amplitude, 1e-300) / max(residual.amplitude, 1e-300))


@dataclass
class IdentificationResult:
    method: str
    harmonic_order: int
    status: str  # ok | below_target | no_authority | failed
    theta_cos: float  # rad
    theta_sin: float  # rad
    residual: Phasor  # h-th phasor with theta applied, full scale
    uncompensated: Phasor  # h-th phasor with theta = 0, full scale
    plant_time_s: float
    windows_used: int
    windows_discarded: int = 0
    message: str = ""
    s_model: complex | None = None  # S_hat of eq. 14-20, full scale per rad
    s_measured: complex | None = None
    target_db: float = 40.0  # the suppression `ok` requires
    noise_floor_db: float | None = None  # rms noise phasor of the final window against |uncompensated|
    # the torque the point ran at: the drive's torque actual, mean over the measurement (None: not known)
    torque_actual_nm: float | None = None
    details: dict[str, Any] = field(default_factory=dict)
    traces: dict[str, Any] = field(default_factory=dict)

    @property
    def gamma_deg(self) -> float:
        return math.degrees(gamma_delta(self.theta_cos, self.theta_sin)[0])

    @property
    def delta_deg(self) -> float:
        return math.degrees(gamma_delta(self.theta_cos, self.theta_sin)[1])

    @property
    def suppression_db(self) -> float:
        return suppression_db(self.uncompensated, self.residual)

    def second_harmonic(self) -> dict[str, Any] | None:
        """Order 2h before (theta = 0) and after (theta applied), from the order spectra of the reference and
        the final window (traces spectrum_before / spectrum_after, whole periods of both orders): the paper's
        warning in numbers (sec. 2.4, eq. 5-6), cancelling order h by voltage-angle injection raises order 2h
        by the gamma^2 term. `rise_db` > 0: raised. `noise_fs`: the rms amplitude a phasor of pure noise shows
        in the final window (sqrt(2) sigma, the sensor's white noise the same at every order): a level within a
        few of it is noise, not the order. None
        without both spectra or when 2h is beyond them."""
        before = self.traces.get("spectrum_before") or []
        after = self.traces.get("spectrum_after") or []
        order = 2 * self.harmonic_order
        if len(before) < order or len(after) < order or self.noise_floor_db is None:
            return None
        before_fs, after_fs = float(before[order - 1]), float(after[order - 1])
        return {
            "order": order,
            "uncompensated_fs": before_fs,
            "compensated_fs": after_fs,
            "rise_db": 20.0 * math.log10(max(after_fs, 1e-300) / max(before_fs, 1e-300)),
            "noise_fs": self.uncompensated.amplitude * 10.0 ** (self.noise_floor_db / 20.0),
        }
