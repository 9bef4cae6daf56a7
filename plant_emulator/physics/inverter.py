"""The inverter between the firmware's u* and the machine: 1.5-period delay, zero-order hold, dead time.

Delay: u*(k) is applied during period k+1 (one period computation + ZOH = 1.5 T_s, Table 1). The
firmware's inverse Park uses the angle advanced to the middle of that period (P_ANGLE_COMP, standard
practice); the inverter holds the alpha-beta vector over the period, so the dq average of the applied
voltage is u* sinc(w_e T_s/2) (and rotated by -1.5 w_e T_s without angle compensation): `zoh_average`,
`applied_voltage`.

Dead time: per phase x the voltage error -U_dc T_dead f_pwm sgn(i_x), averaged over the period (sgn
linear within the larger of +-i_zc and half the current change per period), transformed to dq with
the electrical angle at the middle of the period: its own 6k harmonics (`dead_time_voltage`).
Units: V, A, s, rad, rad/s.
"""

from __future__ import annotations

import math

from numba import njit

SQRT3 = math.sqrt(3.0)

# ---- parameters (indices into p) ----
P_T_DEAD = 36  # s, inverter dead time (0: off)
P_F_PWM = 37  # Hz, PWM frequency
P_I_ZC = 38  # A, dead-time sign(i) is linear within +-i_zc
P_ANGLE_COMP = 40  # 1: inverse Park with the angle advanced by 1.5 w_e T_s

# ---- state (indices into x) ----
X_UD_APP = 2  # V, voltage computed last period, applied (ZOH) during this one
X_UQ_APP = 3


@njit(cache=True, inline="always")
def zoh_average(w_e, ts, angle_comp):
    """Per chunk: (app_c, app_s, rot_c, rot_s). The dq average over one period of the held voltage is
    u* (app_c + j app_s) = u* sinc(w_e T_s/2) e^{j rho}, rho = 0 with angle compensation, else
    -1.5 w_e T_s; (rot_c, rot_s) = (cos, sin)(w_e T_s/2) rotate the sample angle to the middle of the
    period (dead time)."""
    half = 0.5 * w_e * ts
    sinc = math.sin(half) / half if abs(half) > 1e-9 else 1.0
    rho = 0.0 if angle_comp else -3.0 * half
    return sinc * math.cos(rho), sinc * math.sin(rho), math.cos(half), math.sin(half)


@njit(cache=True, inline="always")
def applied_voltage(ud_app, uq_app, app_c, app_s, ed, eq):
    """dq average of the voltage the machine sees during the period: the held u* rotated and scaled
    by (app_c, app_s) from `zoh_average`, plus the dead-time error (ed, eq)."""
    return ud_app * app_c - uq_app * app_s + ed, ud_app * app_s + uq_app * app_c + eq


@njit(cache=True, inline="always")
def dead_time_voltage(i_d, i_q, cphi, sphi, rot_c, rot_s, w_e, ts, dt_amp, inv_izc):
    """dq dead-time voltage error averaged over the next period, V.

    Period average of -dt_amp sgn(i_x(t)) per phase x, dt_amp = U_dc T_dead f_pwm: the phase currents
    at the middle of the period (dq current at the mid-period angle phi_e + w_e T_s/2, from (cphi,
    sphi) and (rot_c, rot_s)), sgn linear within the half change of the current over the period (the
    exact average for a current crossing zero linearly) or the zero-current band 1/inv_izc, whichever
    is wider. Evaluating sgn only at the sample instants instead would tie the crossings to the
    sample grid (120 samples per period at 2000 rpm)."""
    cm = cphi * rot_c - sphi * rot_s
    sm = sphi * rot_c + cphi * rot_s
    ia = i_d * cm - i_q * sm
    ibeta = i_d * sm + i_q * cm
    i_b = -0.5 * ia + 0.5 * SQRT3 * ibeta
    i_c = -ia - i_b
    band = 0.5 * math.sqrt(i_d * i_d + i_q * i_q) * abs(w_e) * ts
    inv_band = inv_izc if band * inv_izc < 1.0 else 1.0 / band
    sa = min(1.0, max(-1.0, ia * inv_band))
    sb = min(1.0, max(-1.0, i_b * inv_band))
    sc = min(1.0, max(-1.0, i_c * inv_band))
    # phase errors -dt_amp s_x -> alpha-beta -> dq at the middle of the period
    e_al = -dt_amp * (2.0 / 3.0) * (sa - 0.5 * sb - 0.5 * sc)
    e_be = -dt_amp * (sb - sc) / SQRT3
    return e_al * cm + e_be * sm, -e_al * sm + e_be * cm
