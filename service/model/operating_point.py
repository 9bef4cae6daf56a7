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

import functools
import math
from dataclasses import asdict, dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from service.settings import MotorSettings


class OperatingPoint(BaseModel):
    """{T*, n, U_dc}: torque command in Nm, mechanical speed in rpm, DC-link voltage in V."""

    # NaN / inf never reach a limit check or the drive: NaN compares False with every limit
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    # no upper bounds here (a speed or a voltage is > 0, whatever the bench): the bench's own limits (safety.*, service/model/limits.py check_limits) judge every value
    # before anything is queued or sent, and name the limit that applies to this bench (a bound here answered
    # first, with a library's words and a limit that was not the bench's)
    torque_nm: float = Field(..., description="torque command T* in Nm (within safety.max_torque_nm)")
    speed_rpm: float = Field(
        ..., gt=0, description="mechanical speed in rpm, > 0 (within safety.min_speed_rpm .. safety.max_speed_rpm)"
    )
    udc_v: float = Field(
        12.0, gt=0, description="DC-link voltage in V, > 0 (within safety.min_udc_v .. safety.max_udc_v)"
    )

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

    def as_dict(self) -> dict[str, Any]:
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


# --- the torque-speed envelope ------------------------------------------------------------------------
@dataclass(frozen=True)
class TorqueEnvelope:
    """What the drive can hold at one speed and U_dc, from the NOMINAL motor settings (torque_envelope)."""

    speed_rpm: float
    udc_v: float
    max_torque_nm: float  # the most |torque| within the current and the voltage limit (0 if it holds no current)
    u_limit_v: float  # voltage_margin * U_dc / sqrt(3), V
    holds_currents: bool  # False: the back-EMF is beyond what full field weakening cancels (see torque_envelope)
    max_speed_rpm: float | None  # the speed up to which the currents are held at this U_dc (None: any speed)
    limited_by: str  # "current" (the current limit, base-speed range) or "voltage" (field weakening)


def _voltage_sq_coefficients(motor: MotorSettings, omega_e: float, i_d: float, u_lim: float) -> tuple[float, ...]:
    """|u_dq|^2 - U^2 = a i_q^2 + b i_q + c in steady state at i_d (eq. 18 with d/dt = 0), i_q >= 0."""
    psi_d = motor.l_d_h * i_d + motor.psi_p_vs
    a = omega_e * omega_e * motor.l_q_h * motor.l_q_h + motor.r_s_ohm * motor.r_s_ohm
    b = 2.0 * motor.r_s_ohm * omega_e * (psi_d - motor.l_q_h * i_d)
    c = motor.r_s_ohm * motor.r_s_ohm * i_d * i_d + omega_e * omega_e * psi_d * psi_d - u_lim * u_lim
    return a, b, c


def _max_iq(motor: MotorSettings, omega_e: float, i_d: float, u_lim: float) -> float:
    """The largest i_q >= 0 within the voltage limit and the current limit at i_d (-1 if none: |u| > U at i_q = 0;
    b >= 0 for a positive flux, so both roots are negative when c > 0)."""
    a, b, c = _voltage_sq_coefficients(motor, omega_e, i_d, u_lim)
    if c > 0.0:
        return -1.0
    iq_v = (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    rest = motor.i_max_a * motor.i_max_a - i_d * i_d
    return min(iq_v, math.sqrt(rest) if rest > 0.0 else 0.0)


def _torque(motor: MotorSettings, i_d: float, i_q: float) -> float:
    return 1.5 * motor.pole_pairs * (motor.psi_p_vs + (motor.l_d_h - motor.l_q_h) * i_d) * i_q


def torque_envelope(speed_rpm: float, udc_v: float, motor: MotorSettings, voltage_margin: float) -> TorqueEnvelope:
    """Cached _torque_envelope (a grid asks the same speed and U_dc for every torque; see there)."""
    return _envelope_cached(float(speed_rpm), float(udc_v), motor.model_dump_json(), voltage_margin)


@functools.lru_cache(maxsize=4096)
def _envelope_cached(speed_rpm: float, udc_v: float, motor_json: str, voltage_margin: float) -> TorqueEnvelope:
    return _torque_envelope(speed_rpm, udc_v, MotorSettings.model_validate_json(motor_json), voltage_margin)


def _torque_envelope(speed_rpm: float, udc_v: float, motor: MotorSettings, voltage_margin: float) -> TorqueEnvelope:
    """The most torque the drive's firmware can hold at `speed_rpm` and `udc_v`, from the NOMINAL motor settings
    (never the emulator's truth), and whether it can hold its currents at all.

    Steady state (eq. 18 with d/dt = 0): u_d = R_s i_d - omega_e L_q i_q, u_q = R_s i_q + omega_e (L_d i_d + psi_p);
    torque T = 1.5 N_p (psi_p + (L_d - L_q) i_d) i_q (eq. 20). The firmware keeps |u_dq| <= U =
    voltage_margin U_dc / sqrt(3) and |i_dq| <= I = motor.i_max_a, with i_d <= 0 (field weakening). So
        T_max = max over i_d in [-I, 0] of T(i_d, i_q,max(i_d)),
        i_q,max(i_d) = min(sqrt(I^2 - i_d^2), the larger root of |u|^2 = U^2 in i_q)
    (a scan of i_d, then a golden-section search around the best: T is unimodal along the boundary).
    Below base speed the current limit binds (T_max = k_T I for surface magnets, k_T = 1.5 N_p psi_p); above
    it the voltage limit with field weakening. The currents are held at all only if some i_d in [-I, 0]
    keeps |u| <= U at i_q = 0: |u|^2 = R^2 i_d^2 + omega_e^2 (L_d i_d + psi_p)^2 is least at
        i_d* = -omega_e^2 L_d psi_p / (R^2 + omega_e^2 L_d^2), clamped to [-I, 0];
    beyond that speed the back-EMF exceeds what the DC link can hold even with full field weakening: the
    current controller sits in its voltage limit, the inverter's diodes rectify and the machine brakes
    uncontrolled, whatever torque is asked for (holds_currents False, max_torque_nm 0). For R_s -> 0 and
    L_d = L_q = L that speed is omega_e = U / (psi_p - L I) (if psi_p > L I)."""
    omega_e = abs(speed_rpm) * 2.0 * math.pi / 60.0 * motor.pole_pairs
    u_lim = voltage_margin * udc_v / math.sqrt(3.0)
    i_max = motor.i_max_a
    max_speed = _max_holding_speed_rpm(motor, u_lim)
    r, ld, psi = motor.r_s_ohm, motor.l_d_h, motor.psi_p_vs
    i_d_least = -omega_e * omega_e * ld * psi / (r * r + omega_e * omega_e * ld * ld) if omega_e > 0 else 0.0
    i_d_least = max(-i_max, i_d_least)
    if udc_v <= 0 or _max_iq(motor, omega_e, i_d_least, u_lim) < 0.0:
        return TorqueEnvelope(speed_rpm, udc_v, 0.0, u_lim, False, max_speed, "voltage")

    def torque_at(i_d: float) -> float:
        i_q = _max_iq(motor, omega_e, i_d, u_lim)
        return -1.0 if i_q < 0.0 else _torque(motor, i_d, i_q)

    n_scan = 64
    grid = [-i_max + i_max * k / n_scan for k in range(n_scan + 1)]
    values = [torque_at(i_d) for i_d in grid]
    best = max(range(len(grid)), key=values.__getitem__)
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, n_scan)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
        if torque_at(m1) > torque_at(m2):
            hi = m2
        else:
            lo = m1
    i_d = 0.5 * (lo + hi)
    t_max = max(torque_at(i_d), values[best])
    a, b, c = _voltage_sq_coefficients(motor, omega_e, i_d, u_lim)
    at_voltage_limit = a * _max_iq(motor, omega_e, i_d, u_lim) ** 2 + b * _max_iq(motor, omega_e, i_d, u_lim) + c
    limited_by = "voltage" if at_voltage_limit > -1e-9 * u_lim * u_lim else "current"
    return TorqueEnvelope(speed_rpm, udc_v, max(t_max, 0.0), u_lim, True, max_speed, limited_by)


def _max_holding_speed_rpm(motor: MotorSettings, u_lim: float) -> float | None:
    """The highest speed at which the currents are held at all (torque_envelope): the omega_e at which the least
    |u| at i_q = 0 over i_d in [-I, 0] reaches U, by bisection (|u|_min grows monotonically with omega_e).
    None: any speed (the field can be weakened to zero within the current limit, L_d I >= psi_p)."""
    if motor.l_d_h * motor.i_max_a >= motor.psi_p_vs:
        return None

    def least_u_sq(omega_e: float) -> float:
        r, ld, psi = motor.r_s_ohm, motor.l_d_h, motor.psi_p_vs
        i_d = max(-motor.i_max_a, -omega_e * omega_e * ld * psi / (r * r + omega_e * omega_e * ld * ld))
        return r * r * i_d * i_d + omega_e * omega_e * (ld * i_d + psi) ** 2

    lo, hi = 0.0, 1.0
    while least_u_sq(hi) < u_lim * u_lim:
        hi *= 2.0
        if hi > 1e9:
            return None
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if least_u_sq(mid) < u_lim * u_lim:
            lo = mid
        else:
            hi = mid
    return lo / motor.pole_pairs * 60.0 / (2.0 * math.pi)
