"""The PMSM in dq coordinates: current dynamics, saturation tables, torque with its harmonics.

    L_d di_d/dt = u_d - R i_d + w_e L_q i_q
    L_q di_q/dt = u_q - R i_q - w_e (L_d i_d + psi_p)                           (eq. 18, 19)
discretised exactly (zero-order hold over T_s) with the 2x2 matrix exponential at w_e (`zoh_dq`,
`current_step`); L_d, L_q, psi_p from the saturation tables at the low-pass filtered current
magnitude (`saturated_params`, updated once per chunk by the loop).

    T_em = 1.5 N_p (psi_p i_q + (L_d - L_q) i_d i_q) + d                          (eq. 20 plus d)
    d = sum_k D_k cos(h_k phi_e + phi_Dk)
k = 0 the map's order h (P_H_DIST), k = 1..3 further orders of their own (slotting, saturation: the
12th, 18th), each D_k, phi_Dk bilinear in its own map over (T*, mechanical speed) on the shared axes,
interpolated as the phasor (X, Y) = (D cos phi_D, D sin phi_D) (`map_phasor`). The 2h the injection
makes is not here: it comes from the exact rotation of the voltage (firmware.inject, eq. 3-4).

Units: V, A, Ohm, H, Wb, Nm, rad, rad/s. The scenario's tables live in the flat array `tab` at the
offsets P_SAT_OFF and P_DMAP_OFF.
"""

from __future__ import annotations

import math

from numba import njit

# ---- parameters (indices into p) ----
P_NP = 1  # pole pairs
P_R = 2  # Ohm, true stator resistance
P_LD = 3  # H, true L_d at zero current (times the saturation table factor)
P_LQ = 4  # H
P_PSI = 5  # Wb, true PM flux linkage at zero current (times the table factor)
P_DIST_SCALE = 24  # factor on the whole disturbance map (1; tests/calibration set 0)
P_XH_N = 27  # number of further torque harmonics (0..MAX_FURTHER_HARMONICS), each with its own map
P_XH_OFF = 28  # offset of [their orders (MAX_FURTHER_HARMONICS), then X_k, Y_k (nn*nt each) per order] in tab
P_T_RATED = 29  # Nm
P_H_DIST = 30  # order of the true torque harmonic
P_OFF_DECAY = 35  # per-period factor of the currents with the inverter off
P_SAT_DECAY = 42  # per-period factor of the |i| low-pass that drives the saturation tables
P_SAT_N = 43  # number of points of the saturation tables
P_SAT_OFF = 44  # offset of [i_axis, ld_rel, lq_rel, psi_rel] in tab
P_DMAP_NT = 45  # disturbance map: torque axis length
P_DMAP_NN = 46  # speed axis length
P_DMAP_OFF = 47  # offset of [torque axis, speed axis (rad/s mech), X (nn*nt), Y (nn*nt)] in tab

MAX_FURTHER_HARMONICS = 3  # the map's order and up to 3 more (a drive injects up to 4 orders at once)

# ---- state (indices into x) ----
X_ID = 0  # A, true currents
X_IQ = 1
X_IMAG_F = 17  # A, low-pass filtered current magnitude (saturation)


@njit(cache=True)
def zoh_dq(r_ohm, ld_h, lq_h, omega_e, ts):
    """Exact ZOH discretisation of the dq current equations (eq. 18) at constant w_e:
    i(k+1) = Ad i(k) + Bd u_eff(k), u_eff = u + [0, -w_e psi]. Returns (a00, a01, a10, a11,
    b00, b01, b10, b11) with Ad = expm(A T_s), Bd = A^-1 (Ad - I) B (A is invertible for R > 0)."""
    a = -r_ohm / ld_h
    b = omega_e * lq_h / ld_h
    c = -omega_e * ld_h / lq_h
    d = -r_ohm / lq_h
    # expm of the 2x2 M = A T: e^s (ch I + sh (M - s I)), eigenvalues s +- sqrt(delta)
    s = 0.5 * (a + d) * ts
    q = 0.5 * (a - d) * ts
    delta = q * q + (b * ts) * (c * ts)
    if delta > 0.0:
        rr = math.sqrt(delta)
        ch = math.cosh(rr)
        sh = math.sinh(rr) / rr if rr > 1e-12 else 1.0
    elif delta < 0.0:
        rr = math.sqrt(-delta)
        ch = math.cos(rr)
        sh = math.sin(rr) / rr if rr > 1e-12 else 1.0
    else:
        ch = 1.0
        sh = 1.0
    es = math.exp(s)
    a00 = es * (ch + sh * q)
    a01 = es * sh * b * ts
    a10 = es * sh * c * ts
    a11 = es * (ch - sh * q)
    det = a * d - b * c
    # A^-1 (Ad - I)
    m00 = (d * (a00 - 1.0) - b * a10) / det
    m01 = (d * a01 - b * (a11 - 1.0)) / det
    m10 = (-c * (a00 - 1.0) + a * a10) / det
    m11 = (-c * a01 + a * (a11 - 1.0)) / det
    return a00, a01, a10, a11, m00 / ld_h, m01 / lq_h, m10 / ld_h, m11 / lq_h


@njit(cache=True, inline="always")
def current_step(zoh, i_d, i_q, u_d, u_q):
    """One period of i(k+1) = Ad i(k) + Bd u(k) with zoh = zoh_dq(...) (A). With u the effective
    voltage u + [0, -w_e psi_p] this is the machine (eq. 18-19); the firmware's decoupling runs the
    same step on its nominal model with the injection voltage alone."""
    a00, a01, a10, a11, b00, b01, b10, b11 = zoh
    return (a00 * i_d + a01 * i_q + b00 * u_d + b01 * u_q, a10 * i_d + a11 * i_q + b10 * u_d + b11 * u_q)


@njit(cache=True, inline="always")
def torque(i_d, i_q, psi, ld, lq, n_p):
    """Electromagnetic torque of the fundamental wave, Nm (eq. 20 without d)."""
    return 1.5 * n_p * (psi * i_q + (ld - lq) * i_d * i_q)


@njit(cache=True, inline="always")
def harmonic(c, s, n):
    """(cos(n x), sin(n x)) from (cos x, sin x) for an integer n >= 0, by repeated squaring (a few
    complex multiplications instead of two transcendental calls; error a few ulp)."""
    rc = 1.0
    rs = 0.0
    bc = c
    bs = s
    while n > 0:
        if n & 1:
            t = rc * bc - rs * bs
            rs = rc * bs + rs * bc
            rc = t
        n >>= 1
        if n:
            t = bc * bc - bs * bs
            bs = 2.0 * bc * bs
            bc = t
    return rc, rs


@njit(cache=True, inline="always")
def harmonic_torque(d_x, d_y, cx, sx):
    """D cos(x + phi_D) = X cos x - Y sin x, Nm, from (X, Y) = D (cos phi_D, sin phi_D) and
    (cx, sx) = (cos x, sin x), x = h phi_e."""
    return d_x * cx - d_y * sx


@njit(cache=True)
def _interp_tab(tab, off, n, col, xq):
    """Linear interpolation of column `col` (0: axis) of a table stored column-wise at tab[off:],
    clamped at the ends."""
    if n <= 1:
        return tab[off + col * n]
    if xq <= tab[off]:
        return tab[off + col * n]
    if xq >= tab[off + n - 1]:
        return tab[off + col * n + n - 1]
    j = 0
    while tab[off + j + 1] < xq:
        j += 1
    x0 = tab[off + j]
    x1 = tab[off + j + 1]
    f = (xq - x0) / (x1 - x0)
    return tab[off + col * n + j] * (1.0 - f) + tab[off + col * n + j + 1] * f


@njit(cache=True)
def _axis_pos(tab, off, n, xq):
    """(index j, fraction f) of xq on a strictly increasing axis, clamped."""
    if n <= 1 or xq <= tab[off]:
        return 0, 0.0
    if xq >= tab[off + n - 1]:
        return n - 2, 1.0
    j = 0
    while tab[off + j + 1] < xq:
        j += 1
    return j, (xq - tab[off + j]) / (tab[off + j + 1] - tab[off + j])


@njit(cache=True)
def map_phasor(p, tab, k, torque_nm, w_m):
    """(X, Y) = (D_k cos phi_Dk, D_k sin phi_Dk) of torque harmonic k at (T*, w_m), bilinear on the
    disturbance map's axes: k = 0 the map's order, k = 1..P_XH_N the further orders."""
    nt = int(p[P_DMAP_NT])
    nn = int(p[P_DMAP_NN])
    if nt == 0 or nn == 0:
        return 0.0, 0.0
    off = int(p[P_DMAP_OFF])
    jt, ft = _axis_pos(tab, off, nt, torque_nm)
    jn, fn = _axis_pos(tab, off + nt, nn, w_m)
    if k == 0:
        xo = off + nt + nn
    else:
        xo = int(p[P_XH_OFF]) + MAX_FURTHER_HARMONICS + (k - 1) * 2 * nt * nn
    yo = xo + nt * nn
    jt1 = jt + 1 if nt > 1 else jt
    jn1 = jn + 1 if nn > 1 else jn
    w00 = (1.0 - ft) * (1.0 - fn)
    w01 = ft * (1.0 - fn)
    w10 = (1.0 - ft) * fn
    w11 = ft * fn
    x = (
        w00 * tab[xo + jn * nt + jt]
        + w01 * tab[xo + jn * nt + jt1]
        + w10 * tab[xo + jn1 * nt + jt]
        + w11 * tab[xo + jn1 * nt + jt1]
    )
    y = (
        w00 * tab[yo + jn * nt + jt]
        + w01 * tab[yo + jn * nt + jt1]
        + w10 * tab[yo + jn1 * nt + jt]
        + w11 * tab[yo + jn1 * nt + jt1]
    )
    s = p[P_DIST_SCALE]
    return s * x, s * y


@njit(cache=True)
def disturbance_phasor(p, tab, torque_nm, w_m):
    """(X, Y) of the map's own order h at (T*, w_m) (map_phasor k = 0)."""
    return map_phasor(p, tab, 0, torque_nm, w_m)


@njit(cache=True)
def further_order(p, tab, k):
    """Electrical order of further harmonic k = 1..P_XH_N."""
    return int(tab[int(p[P_XH_OFF]) + k - 1] + 0.5)


@njit(cache=True)
def saturated_params(p, tab, i_mag):
    """True (L_d, L_q, psi_p) at a current magnitude: base values times the table factors."""
    n = int(p[P_SAT_N])
    if n == 0:
        return p[P_LD], p[P_LQ], p[P_PSI]
    off = int(p[P_SAT_OFF])
    return (
        p[P_LD] * _interp_tab(tab, off, n, 1, i_mag),
        p[P_LQ] * _interp_tab(tab, off, n, 2, i_mag),
        p[P_PSI] * _interp_tab(tab, off, n, 3, i_mag),
    )
