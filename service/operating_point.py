"""Operating points and the nominal steady state of the drive at one of them.

The steady state (i_dq, u_dq) is computed from the bench's NOMINAL parameters (settings), as the
drive's own open-loop torque control would (paper sec. 2.1): i_d = 0 below the voltage limit
(surface magnets, MTPA), i_q = T / k_T with k_T = 1.5 N_p psi_p (eq. 20), and u_dq from the dq
voltage equations in steady state (d/dt = 0 in eq. 18):
    u_d = R_s i_d - omega_e L_q i_q
    u_q = R_s i_q + omega_e (L_d i_d + psi_p)
Above the voltage limit U_dc/sqrt(3), i_d < 0 is chosen so that |u_dq| sits on the limit (field
weakening), as the firmware does.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from pydantic import BaseModel, ConfigDict, Field

from service.settings import MotorSettings


class OperatingPoint(BaseModel):
    """{T*, n, U_dc}: torque command in Nm, mechanical speed in rpm, DC-link voltage in V."""
    # NaN / inf never reach a limit check or the drive: NaN compares False with every limit
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    torque_nm: float = Field(..., ge=-50, le=50, description="torque command T* in Nm")
    speed_rpm: float = Field(..., gt=0, le=30000, description="mechanical speed in rpm (> 0)")
    udc_v: float = Field(12.0, gt=0, le=1000, description="DC-link voltage in V")

    def electrical_speed_rad_s(self, pole_pairs: int) -> float:
        return self.speed_rpm * 2.0 * math.pi / 60.0 * pole_pairs

    def label(self) -> str:
        return f"{self.torque_nm:g} Nm, {self.speed_rpm:g} rpm, {self.udc_v:g} V"


@dataclass(frozen=True)
class SteadyState:
    i_d_a: float
    i_q_a: float
    u_d_v: float
    u_q_v: float
    omega_e_rad_s: float
    field_weakening: bool

    @property
    def u_magnitude_v(self) -> float:
        return math.hypot(self.u_d_v, self.u_q_v)

    def as_dict(self) -> dict:
        return asdict(self)


def _voltages(motor: MotorSettings, i_d: float, i_q: float, omega_e: float) -> tuple[float, float]:
    u_d = motor.r_s_ohm * i_d - omega_e * motor.l_q_h * i_q
    u_q = motor.r_s_ohm * i_q + omega_e * (motor.l_d_h * i_d + motor.psi_p_vs)
    return u_d, u_q


def nominal_steady_state(op: OperatingPoint, motor: MotorSettings) -> SteadyState:
    """Steady-state currents and voltages at `op` from nominal parameters (see module doc)."""
    omega_e = op.electrical_speed_rad_s(motor.pole_pairs)
    k_t = 1.5 * motor.pole_pairs * motor.psi_p_vs
    i_q = op.torque_nm / k_t
    u_limit = op.udc_v / math.sqrt(3.0)
    i_d = 0.0
    u_d, u_q = _voltages(motor, i_d, i_q, omega_e)
    weakening = math.hypot(u_d, u_q) > u_limit
    if weakening:
        # bisection on i_d in [-i_max, 0] for |u| = u_limit (|u| grows monotonically with i_d here)
        lo, hi = -motor.i_max_a, 0.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if math.hypot(*_voltages(motor, mid, i_q, omega_e)) > u_limit:
                hi = mid
            else:
                lo = mid
        i_d = lo
        u_d, u_q = _voltages(motor, i_d, i_q, omega_e)
    return SteadyState(i_d, i_q, u_d, u_q, omega_e, weakening)
