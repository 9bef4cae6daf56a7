"""Operating points and the nominal steady state of the drive at one of them.

The steady state (i_dq, u_dq) is computed from the bench's NOMINAL parameters (settings), as the
drive's own open-loop torque control would (paper sec. 2.1): i_d = 0 below the voltage limit
(surface magnets, MTPA), i_q = T / k_T with k_T = 1.5 N_p psi_p (eq. 20), and u_dq from the dq
voltage equations in steady state (d/dt = 0 in eq. 18):
    u_d = R_s i_d - omega_e L_q i_q
    u_q = R_s i_q + omega_e (L_d i_d + psi_p)
Above the voltage limit U_dc/sqrt(3), i_d < 0 is chosen so that |u_dq| sits on the limit (field
weakening), as the firmware does. `field_weakening_onset` gives the speed at which that sets in for a
torque (closed form, with the firmware's voltage margin: settings control.voltage_margin).
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


@dataclass(frozen=True)
class FieldWeakeningOnset:
    """Where field weakening sets in for one torque at one U_dc (see field_weakening_onset)."""

    speed_rpm: float | None  # mechanical rpm; None: no onset (`reason` says why)
    omega_e_rad_s: float | None  # the same as electrical angular speed, rad/s
    i_q_a: float  # the q current the torque needs below the onset, A (|T*| / k_T)
    u_limit_v: float  # voltage_margin * U_dc / sqrt(3), V
    reason: str | None = None


def field_weakening_onset(
    torque_nm: float, udc_v: float, motor: MotorSettings, voltage_margin: float
) -> FieldWeakeningOnset:
    """The speed at which the drive's firmware leaves MTPA for field weakening at torque T* and U_dc,
    from the NOMINAL motor parameters (settings, never the emulator's truth).

    Below the onset the firmware runs i_d = 0 (surface magnets, MTPA) and i_q = |T*| / k_T with
    k_T = 1.5 N_p psi_p (eq. 20; the firmware computes its references from |T*| and |omega_e|, so the
    onset does not depend on the torque's sign). The steady-state dq voltages (eq. 18 with d/dt = 0,
    eq. 19's back-EMF omega_e psi_p) are then
        u_d = -omega_e L_q i_q,   u_q = R_s i_q + omega_e psi_p                        [V]
        |u_dq|^2 = omega_e^2 (L_q^2 i_q^2 + psi_p^2) + 2 R_s i_q psi_p omega_e + R_s^2 i_q^2
    which grows monotonically with omega_e >= 0. The firmware keeps |u_dq| at
    U = voltage_margin U_dc / sqrt(3) (the rest is headroom for its PI), so the onset is the positive
    root of a omega_e^2 + b omega_e + c = 0 with
        a = L_q^2 i_q^2 + psi_p^2 [V^2 s^2],  b = 2 R_s i_q psi_p [V^2 s],  c = R_s^2 i_q^2 - U^2 [V^2]
        omega_e = -2 c / (b + sqrt(b^2 - 4 a c))    (rad/s; the form without cancellation, c < 0)
        n = omega_e / N_p * 60 / (2 pi)               (rpm, mechanical)
    No onset (speed None, `reason` says why): i_q above motor.i_max_a (the firmware limits the
    current: the torque is not reached at any speed), R_s i_q >= U (the limit is reached at
    standstill), U_dc <= 0."""
    k_t = 1.5 * motor.pole_pairs * motor.psi_p_vs  # Nm/A
    i_q = abs(torque_nm) / k_t
    u_lim = voltage_margin * udc_v / math.sqrt(3.0)
    if not (math.isfinite(i_q) and math.isfinite(u_lim)) or udc_v <= 0:
        return FieldWeakeningOnset(None, None, i_q, u_lim, f"no DC link to weaken the field against ({udc_v:g} V)")
    if i_q > motor.i_max_a:
        return FieldWeakeningOnset(
            None,
            None,
            i_q,
            u_lim,
            f"{abs(torque_nm):g} Nm needs i_q = {i_q:.1f} A, above motor.i_max_a = "
            f"{motor.i_max_a:g} A: the torque is not reached at any speed",
        )
    if motor.r_s_ohm * i_q >= u_lim:
        return FieldWeakeningOnset(
            None,
            None,
            i_q,
            u_lim,
            f"R_s i_q = {motor.r_s_ohm * i_q:.2f} V reaches the voltage limit {u_lim:.2f} V "
            "at standstill: the torque is not reached at any speed",
        )
    l_iq, r_iq = motor.l_q_h * i_q, motor.r_s_ohm * i_q
    a = l_iq * l_iq + motor.psi_p_vs * motor.psi_p_vs
    b = 2.0 * r_iq * motor.psi_p_vs
    c = r_iq * r_iq - u_lim * u_lim  # products, not **: an absurd U_dc gives inf here, not OverflowError
    denominator = b + math.sqrt(b * b - 4.0 * a * c)
    if denominator <= 0.0:  # U underflows to 0 (a DC link of 1e-300 V): the limit is there at standstill
        return FieldWeakeningOnset(None, None, i_q, u_lim, f"the voltage limit {u_lim:g} V is reached at standstill")
    omega_e = -2.0 * c / denominator
    speed_rpm = omega_e / motor.pole_pairs * 60.0 / (2.0 * math.pi)
    if not math.isfinite(speed_rpm):
        return FieldWeakeningOnset(None, None, i_q, u_lim, "the onset lies beyond any finite speed")
    return FieldWeakeningOnset(speed_rpm, omega_e, i_q, u_lim)


def field_weakening_onset_rpm(
    torque_nm: float, udc_v: float, motor: MotorSettings, voltage_margin: float, max_speed_rpm: float | None = None
) -> float | None:
    """Mechanical speed (rpm) at which field weakening sets in (field_weakening_onset), or None when
    there is none, or it lies above `max_speed_rpm` (beyond any speed of interest, e.g. safety.max_speed_rpm)."""
    onset = field_weakening_onset(torque_nm, udc_v, motor, voltage_margin).speed_rpm
    if onset is None or (max_speed_rpm is not None and onset > max_speed_rpm):
        return None
    return onset
