"""The inverter between the firmware's u* and the machine: 1.5-period delay, zero-order hold, dead time.

Delay: u*(k) is applied during period k+1 (one period computation + ZOH = 1.5 T_s, Table 1). The
firmware's inverse Park uses the angle advanced to the middle of that period (P_ANGLE_COMP, standard
practice); the inverter holds the alpha-beta vector over the period, so the dq average of the applied
voltage is u* sinc(w_e T_s/2) (and rotated by -1.5 w_e T_s without angle compensation): `zoh_average`,
`applied_voltage`.

Dead time: per phase x the voltage error -U_dc T_dead f_pwm sgn(i_x) (sgn linear within +-i_zc),
averaged exactly over the period along the phase current's own path from its value at the start to
its value at the end of the period, transformed to dq with the electrical angle at the middle of the
period: its own 6k harmonics (`dead_time_voltage`; the loop predicts the end value with the error
itself, a few fixed-point passes).
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
def _soft_sign_mean(i0, i1, izc):
    """Mean of clip(i / izc, -1, 1) over the period for a phase current going linearly from i0 to i1
    (exact: the difference of the antiderivative F(i) = i^2/(2 izc) inside the band, |i| - izc/2
    outside, over i1 - i0)."""
    di = i1 - i0
    if abs(di) <= 1e-9 * izc:
        return min(1.0, max(-1.0, 0.5 * (i0 + i1) / izc))
    f0 = i0 * i0 / (2.0 * izc) if abs(i0) < izc else abs(i0) - 0.5 * izc
    f1 = i1 * i1 / (2.0 * izc) if abs(i1) < izc else abs(i1) - 0.5 * izc
    return (f1 - f0) / di


@njit(cache=True, inline="always")
def dead_time_voltage(i0_d, i0_q, i1_d, i1_q, cphi, sphi, rot_c, rot_s, dt_amp, izc):
    """dq dead-time voltage error averaged over the period, V, from the dq currents at its start
    (i0, angle phi_e) and at its end (i1, angle phi_e + w_e T_s): per phase the exact period mean of
    -dt_amp sgn(i_x) (sgn linear within +-izc) for a phase current going linearly between its start
    and end values, so a zero crossing counts by where it falls in the period, whatever the slope
    (harmonic currents, the dead time's own flattening of the current near zero). Transformed to dq
    with the electrical angle at the middle of the period. A band fixed by the fundamental's slope
    instead tied the result to where the crossings fell on the sample grid, a phase that a speed with a
    whole number of samples per turn kept for a whole run (a run's history changed the harmonic)."""
    # phase currents at the start and at the end of the period
    c1 = cphi * (rot_c * rot_c - rot_s * rot_s) - sphi * (2.0 * rot_c * rot_s)
    s1 = sphi * (rot_c * rot_c - rot_s * rot_s) + cphi * (2.0 * rot_c * rot_s)
    ia0 = i0_d * cphi - i0_q * sphi
    ibe0 = i0_d * sphi + i0_q * cphi
    ia1 = i1_d * c1 - i1_q * s1
    ibe1 = i1_d * s1 + i1_q * c1
    ib0 = -0.5 * ia0 + 0.5 * SQRT3 * ibe0
    ib1 = -0.5 * ia1 + 0.5 * SQRT3 * ibe1
    sa = _soft_sign_mean(ia0, ia1, izc)
    sb = _soft_sign_mean(ib0, ib1, izc)
    sc = _soft_sign_mean(-ia0 - ib0, -ia1 - ib1, izc)
    cm = cphi * rot_c - sphi * rot_s
    sm = sphi * rot_c + cphi * rot_s
    e_al = -dt_amp * (2.0 / 3.0) * (sa - 0.5 * sb - 0.5 * sc)
    e_be = -dt_amp * (sb - sc) / SQRT3
    return e_al * cm + e_be * sm, -e_al * sm + e_be * cm
