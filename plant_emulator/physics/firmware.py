"""Drive firmware at the controller rate, with its NOMINAL parameters ([firmware] of the scenario).

Chunk-rate task (every `chunk` samples, like a real drive's 1 kHz torque task), `current_reference`:
  torque -> current references (feed-forward): MTPA (i_d = 0 for L_d = L_q, else the MTPA curve),
  and above the voltage limit field weakening: i_d < 0 such that the nominal steady-state |u_dq| =
  margin * U_dc/sqrt(3) (on the side of the constant-torque curve nearer MTPA); current limit I_max
  (i_d has priority). In LUT mode the same task takes theta at the shaft's speed from the speed
  schedule the slow firmware made of its LUT for the piece (`scheduled_theta`): a drive looks its LUT
  up in its torque task, so theta follows a speed ramp within a piece, not once per piece.
Per control period k (paper section 2, Fig. 3):
  PI         `pi_current`: u = K_p e + integral + feed-forward of back-EMF and cross coupling computed
             from the REFERENCES (not the measured currents), |u| <= U_dc/sqrt(3) (vector scaling,
             back-calculation anti-windup, T_t = K_p/K_i). K_p = 2 pi f_bw L_nom, K_i = 2 pi f_bw R_nom.
  FW loop    `field_weakening`: a slow voltage loop (as drives do to survive parameter errors) adds
             delta i_d <= 0 while the PI output |u| exceeds fw_target U_dc/sqrt(3):
             d(delta i_d)/dt = -w_fw (|u| - u_target) / (|w_e| L_d,nom), i_q cut to the current limit.
  injection  v_inj = sum_k theta_cos,k cos(h_k phi_e) + theta_sin,k sin(h_k phi_e)   (eq. 3, 12)
             (the main order h and up to 3 further ones, each its own theta; one rotation by the sum)
             `inject`: default u* = R(v_inj) u (exact rotation, |u*| = |u|, eq. 2-4);
             eq. 11 variant (S_VEST): u* = u + (R(v_inj) - I) u_hat0, u_hat0 = sat(G_EM^-1 G_cl i*)
             from the nominal model (`voltage_estimate`; the injection no longer follows the PI
             output's harmonics).
  decoupl.   (S_DECOUPLING, section 3.1) the harmonic currents the applied injection voltage u* - u
             causes are estimated with the nominal model (machine.current_step on the nominal ZOH
             matrices) and subtracted from the measured currents before the PI.
  estimate   `torque_estimate`: 0x6077 from the measured currents and the nominal parameters.
Units: V, A, Ohm, H, Wb, Nm, rad, rad/s.
"""

from __future__ import annotations

import math

from numba import njit

from .machine import torque as _torque_of

SQRT3 = math.sqrt(3.0)

# ---- parameters (indices into p) ----
P_TS = 0  # s, control period (the whole emulator steps at the controller rate)
P_R_NOM = 6  # Ohm, the firmware's nominal values
P_LD_NOM = 7  # H
P_LQ_NOM = 8  # H
P_PSI_NOM = 9  # Wb
P_KP_D = 10  # V/A
P_KP_Q = 11
P_KI_D = 12  # V/(A s)
P_KI_Q = 13
P_IMAX = 14  # A, current vector limit
P_V_MARGIN = 39  # field weakening targets margin * U_dc/sqrt(3)
P_W_BW = 41  # rad/s, nominal current-loop bandwidth (G_cl of eq. 11)
P_FW_BW = 48  # rad/s, bandwidth of the closed-loop field weakening (0: feed-forward only)
P_FW_TARGET = 49  # the voltage loop holds |u| <= target * U_dc/sqrt(3)

# ---- setpoints (indices into sp), constant over one call ----
S_POWER = 0  # 1: power stage on (OPERATION_ENABLED and DC link ok)
S_TORQUE_NM = 1  # torque command T*
S_THETA_COS = 2  # rad, already clamped and zero when injection is off
S_THETA_SIN = 3
S_H = 4  # harmonic order used by the firmware's injection
S_DECOUPLING = 5  # 0/1
S_UDC_V = 6  # DC-link voltage
S_VEST = 10  # 0/1, eq. 11: G_comp from the estimate u_hat_dq,0 instead of the PI output
# further injection orders k = 1..3 (0 order: unused): v_inj = sum over all orders (`injection_angle`)
S_XH_ORDER = 13  # 13, 14, 15: h_k
S_XH_COS = 16  # 16, 17, 18: rad, theta_cos of order k, clamped with the others (the sum of |theta|)
S_XH_SIN = 19  # 19, 20, 21
MAX_INJECTION_ORDERS = 4  # the main order and 3 further ones
INDEX_BLOCKS = {"S_XH_ORDER": 3, "S_XH_COS": 3, "S_XH_SIN": 3}  # indices that start a block of this many

# ---- state (indices into x) ----
X_INT_D = 4  # V, PI integrators
X_INT_Q = 5
X_VD_APP = 12  # V, injection part u* - u being applied (decoupling estimator input)
X_VQ_APP = 13
X_IHAT_D = 14  # A, estimated injection-caused currents (decoupling)
X_IHAT_Q = 15
X_IF_D = 18  # A, eq. 11: i* through the nominal closed loop G_cl
X_IF_Q = 19
X_FW_DID = 20  # A, closed-loop field weakening: i_d correction (<= 0)


# ------------------------------------------------------------------------------------------------
# chunk rate: torque -> current references (nominal parameters)


@njit(cache=True)
def mtpa_id(i_q, psi, ld, lq):
    """MTPA d current for a q current: dT/dbeta = 0 at constant |i|. i_d = 0 for L_d = L_q, else
    i_d = (psi - sqrt(psi^2 + 4 (L_q - L_d)^2 i_q^2)) / (2 (L_q - L_d))."""
    dl = lq - ld
    if abs(dl) < 1e-12 * (abs(ld) + abs(lq)):
        return 0.0
    return (psi - math.sqrt(psi * psi + 4.0 * dl * dl * i_q * i_q)) / (2.0 * dl)


@njit(cache=True)
def _u_mag(i_d, i_q, w_e, r, ld, lq, psi):
    u_d = r * i_d - w_e * lq * i_q
    u_q = r * i_q + w_e * (ld * i_d + psi)
    return math.sqrt(u_d * u_d + u_q * u_q)


@njit(cache=True)
def _iq_for_torque(torque, i_d, psi, ld, lq, n_p):
    den = 1.5 * n_p * (psi + (ld - lq) * i_d)
    if den <= 1e-12:
        return 0.0
    return torque / den


@njit(cache=True)
def _iq_on_voltage_limit(i_d, aw, u_lim, r, ld, lq, psi, i_max):
    """Largest i_q >= 0 with |u_ss(i_d, i_q)| <= u_lim and |i| <= I_max (0 if none):
    |u|^2 = a i_q^2 + b i_q + c with a = w^2 L_q^2 + R^2, b = 2 R w (psi_d - L_q i_d),
    c = (R i_d)^2 + w^2 psi_d^2 - u_lim^2, psi_d = L_d i_d + psi."""
    psi_d = ld * i_d + psi
    a = aw * aw * lq * lq + r * r
    b = 2.0 * r * aw * (psi_d - lq * i_d)
    c = (r * i_d) ** 2 + aw * aw * psi_d * psi_d - u_lim * u_lim
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return 0.0
    iq = (-b + math.sqrt(disc)) / (2.0 * a)
    rest = i_max * i_max - i_d * i_d
    iq_i = math.sqrt(rest) if rest > 0.0 else 0.0
    return max(0.0, min(iq, iq_i))


@njit(cache=True)
def _max_torque_point(aw, u_lim, r, ld, lq, psi, n_p, i_max, sgn):
    """Maximum torque within the voltage and the current limit (MTPV / current limit corner): a scan
    over i_d in [-I_max, 0] (the torque is 0 where the voltage ellipse leaves no i_q), then a
    golden-section search around the best point."""
    n_scan = 64
    best = 0
    t_best = -1.0
    for j in range(n_scan + 1):
        i_d = -i_max + i_max * j / n_scan
        t = _torque_of(i_d, _iq_on_voltage_limit(i_d, aw, u_lim, r, ld, lq, psi, i_max), psi, ld, lq, n_p)
        if t > t_best:
            t_best = t
            best = j
    lo = -i_max + i_max * max(best - 1, 0) / n_scan
    hi = -i_max + i_max * min(best + 1, n_scan) / n_scan
    g = 0.6180339887498949
    for _ in range(60):
        m1 = hi - g * (hi - lo)
        m2 = lo + g * (hi - lo)
        t1 = _torque_of(m1, _iq_on_voltage_limit(m1, aw, u_lim, r, ld, lq, psi, i_max), psi, ld, lq, n_p)
        t2 = _torque_of(m2, _iq_on_voltage_limit(m2, aw, u_lim, r, ld, lq, psi, i_max), psi, ld, lq, n_p)
        if t1 > t2:
            hi = m2
        else:
            lo = m1
    i_d = 0.5 * (lo + hi)
    return i_d, sgn * _iq_on_voltage_limit(i_d, aw, u_lim, r, ld, lq, psi, i_max)


@njit(cache=True)
def current_reference(torque_nm, w_e, udc_v, r, ld, lq, psi, n_p, i_max, margin):
    """The firmware's open-loop torque control (paper Fig. 3, 'MTPA/MTPV' block) with its NOMINAL
    parameters. Returns (i_d*, i_q*) in A.

    1. MTPA: i_q from T* by bisection on T(i_d_mtpa(i_q), i_q) = T* (monotonic), i_d on the MTPA curve.
    2. If the nominal steady-state |u_dq| exceeds margin * U_dc/sqrt(3): field weakening along the
       constant-torque curve i_q = T*/(1.5 N_p (psi + (L_d - L_q) i_d)): find the i_d in [-I_max, i_d_mtpa]
       of least |u| (golden section), then bisect between it and MTPA for |u| on the limit. If even the
       least |u| is above it, the torque is out of reach at this speed and U_dc: the point of most
       torque within the voltage and the current limit instead (MTPV / current-limit corner).
    3. Current limit: beyond I_max in field weakening, the most-torque point within both limits again;
       below base speed |i| <= I_max with priority to i_d (i_q, hence the torque, is reduced)."""
    sgn = 1.0 if torque_nm >= 0.0 else -1.0
    t = abs(torque_nm)
    # 1. MTPA
    lo = 0.0
    hi = i_max
    if _torque_of(mtpa_id(hi, psi, ld, lq), hi, psi, ld, lq, n_p) <= t:
        i_q = hi
    else:
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            if _torque_of(mtpa_id(mid, psi, ld, lq), mid, psi, ld, lq, n_p) < t:
                lo = mid
            else:
                hi = mid
        i_q = 0.5 * (lo + hi)
    i_d = mtpa_id(i_q, psi, ld, lq)
    # 2. field weakening
    u_fw = margin * udc_v / SQRT3
    aw = abs(w_e)
    if udc_v > 0.0 and _u_mag(i_d, i_q, aw, r, ld, lq, psi) > u_fw:
        # |u| along the constant-torque curve falls as i_d goes negative, down to a minimum (the R i_d
        # drop makes it rise again near -I_max): golden-section search for that minimum first
        lo = -i_max
        hi = i_d
        g = 0.6180339887498949
        for _ in range(60):
            m1 = hi - g * (hi - lo)
            m2 = lo + g * (hi - lo)
            if _u_mag(m1, _iq_for_torque(t, m1, psi, ld, lq, n_p), aw, r, ld, lq, psi) < _u_mag(
                m2, _iq_for_torque(t, m2, psi, ld, lq, n_p), aw, r, ld, lq, psi
            ):
                hi = m2
            else:
                lo = m1
        id_min = 0.5 * (lo + hi)
        if _u_mag(id_min, _iq_for_torque(t, id_min, psi, ld, lq, n_p), aw, r, ld, lq, psi) > u_fw:
            # the torque is out of reach at this speed and U_dc: the most torque within both limits
            return _max_torque_point(aw, u_fw, r, ld, lq, psi, n_p, i_max, sgn)
        else:
            lo = id_min
            hi = i_d
            for _ in range(50):
                mid = 0.5 * (lo + hi)
                if _u_mag(mid, _iq_for_torque(t, mid, psi, ld, lq, n_p), aw, r, ld, lq, psi) > u_fw:
                    hi = mid
                else:
                    lo = mid
            i_d = 0.5 * (lo + hi)
        i_q = _iq_for_torque(t, i_d, psi, ld, lq, n_p)
    # 3. current limit: beyond I_max the most torque within both limits
    if i_d * i_d + i_q * i_q > i_max * i_max * (1.0 + 1e-12):
        if udc_v > 0.0 and _u_mag(i_d, i_q, aw, r, ld, lq, psi) > 0.999 * u_fw:
            return _max_torque_point(aw, u_fw, r, ld, lq, psi, n_p, i_max, sgn)
    if i_d < -i_max:
        i_d = -i_max
    rest = i_max * i_max - i_d * i_d
    iq_max = math.sqrt(rest) if rest > 0.0 else 0.0
    if i_q > iq_max:
        i_q = iq_max
    return i_d, sgn * i_q


# ------------------------------------------------------------------------------------------------
# per control period


@njit(cache=True, inline="always")
def pi_current(id_ref, iq_ref, id_fb, iq_fb, int_d, int_q, w_e, kp_d, kp_q, ki_d, ki_q, ld_nom, lq_nom, psi_nom, u_lim):
    """The dq current PI with feed-forward (paper Fig. 3). ki_d, ki_q are K_i T_s (V/A).

    u_d = K_p,d e_d + integral_d - w_e L_q,nom i_q*
    u_q = K_p,q e_q + integral_q + w_e (L_d,nom i_d* + psi_p,nom),  e = i* - i_fb,
    scaled as a vector to |u| <= u_lim = U_dc/sqrt(3). Anti-windup by back-calculation: the
    integrators integrate always and, while the limit cuts, track back by the part it cut off with
    the time constant T_t = K_p/K_i per axis: int += K_i T_s e - (K_i T_s/K_p) (u - u_lim u/|u|).
    Freezing them in the limit (conditional integration) kept whatever value they had when the
    saturation began: at a point the true machine cannot reach (seeded psi_p, past full field
    weakening) the PI sat in the limit for good and its voltage angle, hence the currents, the torque
    and the harmonic, depended on the run's history. Returns (u_d, u_q, |u| before the limit,
    integrals)."""
    e_d = id_ref - id_fb
    e_q = iq_ref - iq_fb
    # feed-forward of cross coupling and back-EMF from the references (see module doc)
    u_d = kp_d * e_d + int_d - w_e * lq_nom * iq_ref
    u_q = kp_q * e_q + int_q + w_e * (ld_nom * id_ref + psi_nom)
    mag = math.sqrt(u_d * u_d + u_q * u_q)
    int_d += ki_d * e_d
    int_q += ki_q * e_q
    if mag > u_lim:
        scale = u_lim / mag if mag > 0.0 else 0.0
        # back-calculation: the part of u the limit cut off, fed back at K_i T_s / K_p
        cut = 1.0 - scale
        if kp_d > 0.0:
            int_d -= ki_d / kp_d * cut * u_d
        if kp_q > 0.0:
            int_q -= ki_q / kp_q * cut * u_q
        u_d *= scale
        u_q *= scale
    return u_d, u_q, mag, int_d, int_q


@njit(cache=True, inline="always")
def field_weakening(fw_did, u_mag, fw_gain, u_target, fw_did_min, id_ff, iq_ff, i_max2):
    """One period of the closed-loop field weakening on the PI output magnitude: delta i_d <- delta
    i_d - fw_gain (|u| - u_target), fw_gain = w_fw T_s / (|w_e| L_d,nom) (A/V), clamped to
    [fw_did_min, 0]; i_q* cut so that |i*| <= I_max (i_max2 = I_max^2, A^2) while weakening.
    Returns (delta i_d, i_d*, i_q*)."""
    fw_did -= fw_gain * (u_mag - u_target)
    if fw_did > 0.0:
        fw_did = 0.0
    elif fw_did < fw_did_min:
        fw_did = fw_did_min
    id_ref = id_ff + fw_did
    if fw_did < 0.0:
        rest = i_max2 - id_ref * id_ref
        iq_cap = math.sqrt(rest) if rest > 0.0 else 0.0
        iq_ref = min(abs(iq_ff), iq_cap) * (1.0 if iq_ff >= 0.0 else -1.0)
    else:
        iq_ref = iq_ff
    return fw_did, id_ref, iq_ref


@njit(cache=True, inline="always")
def voltage_estimate(id_ref, iq_ref, if_d, if_q, w_e, w_bw, g_cl, r_nom, ld_nom, lq_nom, psi_nom, u_lim):
    """Eq. 11: u_hat0 = sat(G_EM^-1 G_cl i*) from the nominal model, with G_cl first order at the
    current-loop bandwidth w_bw (rad/s), discretised exactly (g_cl = 1 - exp(-w_bw T_s)); (if_d, if_q)
    is i* through G_cl (A). Returns (u_hat_d, u_hat_q, if_d, if_q) with |u_hat| <= u_lim (V)."""
    did = w_bw * (id_ref - if_d)
    diq = w_bw * (iq_ref - if_q)
    uh_d = r_nom * if_d + ld_nom * did - w_e * lq_nom * if_q
    uh_q = r_nom * if_q + lq_nom * diq + w_e * (ld_nom * if_d + psi_nom)
    uh = math.sqrt(uh_d * uh_d + uh_q * uh_q)
    if uh > u_lim:
        uh_d *= u_lim / uh
        uh_q *= u_lim / uh
    if_d += g_cl * (id_ref - if_d)
    if_q += g_cl * (iq_ref - if_q)
    return uh_d, uh_q, if_d, if_q


@njit(cache=True, inline="always")
def scheduled_theta(schedule, w_m):
    """(theta_cos, theta_sin) in rad at shaft speed w_m (rad/s) from a speed schedule: rows (w_m rad/s,
    theta_cos, theta_sin) at a uniform speed step, linear between rows, clamped at the first and last."""
    n = schedule.shape[0]
    f = 0.0 if n == 1 else (w_m - schedule[0, 0]) / (schedule[1, 0] - schedule[0, 0])
    if not f > 0.0:  # below the first row (or NaN)
        return schedule[0, 1], schedule[0, 2]
    if f >= n - 1:
        return schedule[n - 1, 1], schedule[n - 1, 2]
    j = int(f)
    a = f - j
    return (1.0 - a) * schedule[j, 1] + a * schedule[j + 1, 1], (1.0 - a) * schedule[j, 2] + a * schedule[j + 1, 2]


@njit(cache=True, inline="always")
def injection_angle(theta_cos, theta_sin, cos_h_phi, sin_h_phi):
    """v_inj = x^T theta = theta_cos cos(h phi_e) + theta_sin sin(h phi_e), rad (eq. 3, 12)."""
    return theta_cos * cos_h_phi + theta_sin * sin_h_phi


@njit(cache=True, inline="always")
def inject(u_d, u_q, uh_d, uh_q, v_inj, vest, u_lim):
    """The voltage the inverter is told, u*, from the PI output u and the injection angle v_inj.
    Default: u* = R(v_inj) u, the exact rotation (|u*| = |u|, eq. 2-4). vest (eq. 11 variant):
    u* = u + (R(v_inj) - I) u_hat0, scaled to |u*| <= u_lim."""
    cv = math.cos(v_inj)
    sv = math.sin(v_inj)
    if vest:
        u_ds = u_d + (cv - 1.0) * uh_d - sv * uh_q
        u_qs = u_q + sv * uh_d + (cv - 1.0) * uh_q
        m2 = math.sqrt(u_ds * u_ds + u_qs * u_qs)
        if m2 > u_lim:
            u_ds *= u_lim / m2
            u_qs *= u_lim / m2
    else:
        u_ds = u_d * cv - u_q * sv
        u_qs = u_d * sv + u_q * cv
    return u_ds, u_qs


@njit(cache=True, inline="always")
def torque_estimate(i_d, i_q, k_t_nom, n_p, ld_nom, lq_nom):
    """The drive's torque actual (0x6077), Nm: eq. 20 with the nominal parameters and the measured
    currents, k_t_nom = 1.5 N_p psi_p,nom."""
    return k_t_nom * i_q + 1.5 * n_p * (ld_nom - lq_nom) * i_d * i_q
