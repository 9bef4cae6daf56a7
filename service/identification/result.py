"""The result of one identification, self-describing enough to store and to redraw its plots."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from service.harmonic import Phasor
from service.secondary_path import gamma_delta

def suppression_db(uncompensated: Phasor, residual: Phasor) -> float:
    """20 log10(|a_uncompensated| / |a_residual|), dB (positive = harmonic reduced)."""
    return 20.0 * math.log10(max(uncompensated.amplitude, 1e-300) / max(residual.amplitude, 1e-300))


@dataclass
class IdentificationResult:
    method: str
    harmonic_order: int
    status: str                       # ok | below_target | no_authority | failed
    theta_cos: float                  # rad
    theta_sin: float                  # rad
    residual: Phasor                  # h-th phasor with theta applied, full scale
    uncompensated: Phasor             # h-th phasor with theta = 0, full scale
    plant_time_s: float
    windows_used: int
    windows_discarded: int = 0
    message: str = ""
    s_model: complex | None = None    # S_hat of eq. 14-20, full scale per rad
    s_measured: complex | None = None
    target_db: float = 40.0           # the suppression `ok` requires
    noise_floor_db: float | None = None   # rms noise phasor of the final window against |uncompensated|
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

    def to_public(self) -> dict[str, Any]:
        def cplx(c: complex | None):
            return None if c is None else {"re": c.real, "im": c.imag, "gain": abs(c),
                                           "phase_deg": math.degrees(math.atan2(c.imag, c.real))}
        return {
            "method": self.method,
            "harmonic_order": self.harmonic_order,
            "status": self.status,
            "message": self.message,
            "gamma_deg": self.gamma_deg,
            "delta_deg": self.delta_deg,
            "theta_cos": self.theta_cos,
            "theta_sin": self.theta_sin,
            "residual": {"a_c": self.residual.a_c, "a_s": self.residual.a_s, "amplitude": self.residual.amplitude},
            "uncompensated": {"a_c": self.uncompensated.a_c, "a_s": self.uncompensated.a_s,
                              "amplitude": self.uncompensated.amplitude},
            "suppression_db": self.suppression_db,
            "target_db": self.target_db,
            "noise_floor_db": self.noise_floor_db,
            "plant_time_s": self.plant_time_s,
            "windows_used": self.windows_used,
            "windows_discarded": self.windows_discarded,
            "s_model": cplx(self.s_model),
            "s_measured": cplx(self.s_measured),
            "details": self.details,
            "traces": self.traces,
        }
