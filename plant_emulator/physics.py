"""Physics of the emulated bench at the controller rate: pure functions over state arrays.

One call of `simulate_chunk` advances drive firmware control loop + PMSM + shaft + load machine +
accelerometer by n control periods T_s (1/16 kHz in paper-bench). Everything is in SI units
(V, A, Ohm, H, Wb, Nm, rad, rad/s, rad/s^2, kg m^2); no CAN, no pty, no threads here, so tests run
the physics directly. The state lives in flat float64 arrays indexed by the X_*/P_*/S_* constants
below (numba compiles them as constants).

Per control period k (paper section 2, Fig. 3):
  firmware   i_q* = T*/(1.5 N_p psi_nom), i_d* = 0 (`torque_to_current_ref`), PI current control in dq
             with pole-zero cancellation (K_p = 2 pi f_bw L_nom, K_i = 2 pi f_bw R_nom) plus feed-forward
             of back-EMF and cross coupling from the references, |u_dq| <= U_dc/sqrt(3) (vector scaling,
             conditional-integration anti-windup).
  injection  v_inj = theta_cos cos(h phi_e) + theta_sin sin(h phi_e)            (eq. 3, 12)
             u*_d = u_d cos v - u_q sin v,  u*_q = u_d sin v + u_q cos v         (eq. 4, exact rotation)
  delay      u*(k) is applied (ZOH in dq) during period k+1: 1 period computation + 0.5 period
             from the ZOH = 1.5 T_s (Table 1, eq. 17)
  PMSM       L_d di_d/dt = u_d - R i_d + w_e L_q i_q
             L_q di_q/dt = u_q - R i_q - w_e (L_d i_d + psi_p)                   (eq. 18, 19)
             discretised exactly for the ZOH input with the 2x2 matrix exponential at w_e(k)
  torque     T_em = 1.5 N_p (psi_p i_q + (L_d - L_q) i_d i_q) + d                (eq. 20 plus d)
             d = D cos(h phi_e + phi_D) + D_2 cos(2 h phi_e + phi_D2), D = d_0 + d_2 (T*/T_rated)^2
  shaft      J dw_m/dt = T_em + T_lm - B w_m  (T_lm: load machine torque: ramped speed reference,
             PI speed loop plus acceleration feed-forward)
  sensor     alpha_meas = H(z) dw_m/dt + noise, H = J G_Salpha (zero z, poles p, H(0) = 1,
             section 2.3), bilinear with pre-warping at |p|; int16 counts of the full scale.
Decoupling (paper section 3.1): the harmonic currents the injection causes are estimated with the
nominal model driven by the delayed injection voltage u* - u and subtracted from the measured
currents, so the nominal PI does not see them.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

SQRT3 = math.sqrt(3.0)
TWO_PI = 2.0 * math.pi

# ---- parameter vector (truth, firmware nominal, sensor, load) ----
P_TS = 0            # s, control period
P_NP = 1            # pole pairs
P_R = 2             # Ohm, true stator resistance
P_LD = 3            # H
P_LQ = 4            # H
P_PSI = 5           # Wb, true PM flux linkage
P_R_NOM = 6         # firmware's nominal values
P_LD_NOM = 7
P_LQ_NOM = 8
P_PSI_NOM = 9
P_KP_D = 10         # V/A
P_KP_Q = 11
P_KI_D = 12         # V/(A s)
P_KI_Q = 13
P_IMAX = 14         # A, current vector limit
P_J = 15            # kg m^2
P_B = 16            # Nm/(rad/s), viscous friction
P_H_B0 = 17         # sensor biquad (direct form II transposed), normalised a0 = 1
P_H_B1 = 18
P_H_B2 = 19
P_H_A1 = 20
P_H_A2 = 21
P_ALPHA_FS = 22     # rad/s^2, sensor full scale (+-32767 counts)
P_NOISE = 23        # rad/s^2, sensor noise standard deviation
P_D0 = 24           # Nm
P_D2 = 25           # Nm at rated torque (times (T*/T_rated)^2)
P_PHI_D = 26        # rad
P_D2_RATIO = 27     # D_2 / D
P_PHI_D2 = 28       # rad
P_T_RATED = 29      # Nm
P_H_DIST = 30       # order of the true torque harmonic
P_LOAD_KP = 31      # Nm/(rad/s)
P_LOAD_KI = 32      # Nm/rad
P_LOAD_RAMP = 33    # rad/s^2 (mechanical), ramp of the speed reference
P_LOAD_TMAX = 34    # Nm
P_OFF_DECAY = 35    # per-period factor of the currents with the inverter off
N_PARAMS = 36

# ---- setpoints, constant over one chunk (applied at its first sample) ----
S_POWER = 0         # 1: power stage on (OPERATION_ENABLED and DC link ok)
S_TORQUE_NM = 1     # torque command T*
S_THETA_COS = 2     # rad, already clamped and zero when injection is off
S_THETA_SIN = 3
S_H = 4             # harmonic order used by the firmware's injection
S_DECOUPLING = 5    # 0/1
S_UDC_V = 6         # DC-link voltage
S_LOAD_ON = 7       # 1: load machine speed loop active
S_LOAD_SPEED = 8    # rad/s, mechanical target speed of the load machine
S_SYNC = 9          # 0/1, level of the DAQ sync flag during this chunk
N_SETPOINTS = 10

# ---- state ----
X_ID = 0            # A, true currents
X_IQ = 1
X_UD_APP = 2        # V, voltage computed last period, applied (ZOH) during this one
X_UQ_APP = 3
X_INT_D = 4         # V, PI integrators
X_INT_Q = 5
X_PHI_E = 6         # rad, electrical angle in [0, 2 pi)
X_OMEGA_M = 7       # rad/s, mechanical speed
X_LOAD_INT = 8      # Nm, load speed-loop integrator
X_LOAD_REF = 9      # rad/s, ramped speed reference
X_H_S1 = 10         # sensor biquad states
X_H_S2 = 11
X_VD_APP = 12       # V, injection part u* - u being applied (decoupling estimator input)
X_VQ_APP = 13
X_IHAT_D = 14       # A, estimated injection-caused currents (decoupling)
X_IHAT_Q = 15
X_SAMPLES = 16      # samples simulated so far
N_STATE = 17

# ---- per-chunk summary ----
Y_UD_SUM = 0        # sum of nominal u_d over the chunk (V)
Y_UQ_SUM = 1
Y_TORQUE_EST_SUM = 2  # firmware torque estimate from measured currents, nominal params (Nm)
Y_OMEGA_SUM = 3
Y_LOAD_TORQUE_SUM = 4
Y_OVER_RANGE = 5    # count of clipped samples
N_SUMMARY = 6

# ---- optional per-sample trace ----
TR_ID = 0
TR_IQ = 1
TR_UD = 2           # nominal control output u_dq (before injection)
TR_UQ = 3
TR_UD_STAR = 4      # after injection (what the inverter is told)
TR_UQ_STAR = 5
TR_TORQUE = 6       # T_em including d
TR_DIST = 7         # d
TR_ALPHA = 8        # true dw_m/dt
TR_ALPHA_MEAS = 9   # sensor output before quantisation
TR_PHI_E = 10
TR_OMEGA_M = 11
TR_V_INJ = 12
TR_T_LOAD = 13      # load machine torque T_lm
N_TRACE = 14

OMEGA_RECOMPUTE_RAD_S = 1e-3  # electrical rad/s change that triggers a new matrix exponential
SYNC_FLAG = 1 << 2
OVER_RANGE_FLAG = 1 << 0


@njit(cache=True)
def torque_to_current_ref(torque_nm, psi_nom_wb, n_p, i_max_a):
    """Open-loop torque control (paper Fig. 3, 'MTPA/MTPV' block), surface-magnet version:
    i_d* = 0, i_q* = T*/(1.5 N_p psi_p), limited to I_max. Returns (i_d*, i_q*) in A.
    Kept separate so MTPA / field weakening can replace it."""
    iq = torque_nm / (1.5 * n_p * psi_nom_wb)
    if iq > i_max_a:
        iq = i_max_a
    elif iq < -i_max_a:
        iq = -i_max_a
    return 0.0, iq


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


@njit(cache=True, nogil=True)
def simulate_chunk(x, p, sp, noise, angle_counts, accel_counts, flags, summary, trace):
    """Advance the bench by n = len(noise) control periods in place.

    x: state (N_STATE), p: parameters (N_PARAMS), sp: setpoints (N_SETPOINTS), noise: n standard
    normal samples for the sensor. Outputs per sample: angle_counts (uint16, phi_e*65536/2pi),
    accel_counts (int16, round(alpha/fs*32767) clipped), flags (uint16: bit 0 over-range,
    bit 2 sync level). summary (N_SUMMARY) receives sums over the chunk. trace: (n, N_TRACE) array
    filled per sample, or shape (0, N_TRACE) to skip recording.
    """
    n = noise.shape[0]
    record = trace.shape[0] >= n
    ts = p[P_TS]
    n_p = p[P_NP]
    r = p[P_R]
    ld = p[P_LD]
    lq = p[P_LQ]
    psi = p[P_PSI]
    ld_nom = p[P_LD_NOM]
    lq_nom = p[P_LQ_NOM]
    psi_nom = p[P_PSI_NOM]
    k_t_nom = 1.5 * n_p * psi_nom
    power = sp[S_POWER] > 0.5
    torque_ref = sp[S_TORQUE_NM] if power else 0.0
    id_ref, iq_ref = torque_to_current_ref(torque_ref, psi_nom, n_p, p[P_IMAX])
    th_c = sp[S_THETA_COS]
    th_s = sp[S_THETA_SIN]
    inject = th_c != 0.0 or th_s != 0.0
    h = sp[S_H]
    decouple = sp[S_DECOUPLING] > 0.5
    u_lim = sp[S_UDC_V] / SQRT3
    load_on = sp[S_LOAD_ON] > 0.5
    load_target = sp[S_LOAD_SPEED]
    sync_bits = SYNC_FLAG if sp[S_SYNC] > 0.5 else 0
    # disturbance amplitude from the operating point (issue 2 map: quadratic in T*/T_rated)
    t_rel = torque_ref / p[P_T_RATED]
    d_amp = p[P_D0] + p[P_D2] * t_rel * t_rel
    d2_amp = p[P_D2_RATIO] * d_amp
    h_dist = p[P_H_DIST]
    cos_pd = math.cos(p[P_PHI_D])
    sin_pd = math.sin(p[P_PHI_D])
    cos_pd2 = math.cos(p[P_PHI_D2])
    sin_pd2 = math.sin(p[P_PHI_D2])
    b0 = p[P_H_B0]
    b1 = p[P_H_B1]
    b2 = p[P_H_B2]
    a1 = p[P_H_A1]
    a2 = p[P_H_A2]
    fs = p[P_ALPHA_FS]
    sigma = p[P_NOISE]
    counts_per_rad = 65536.0 / TWO_PI
    ramp = p[P_LOAD_RAMP] * ts
    tmax = p[P_LOAD_TMAX]

    i_d = x[X_ID]
    i_q = x[X_IQ]
    ud_app = x[X_UD_APP]
    uq_app = x[X_UQ_APP]
    int_d = x[X_INT_D]
    int_q = x[X_INT_Q]
    phi = x[X_PHI_E]
    w_m = x[X_OMEGA_M]
    load_int = x[X_LOAD_INT]
    load_ref = x[X_LOAD_REF]
    hs1 = x[X_H_S1]
    hs2 = x[X_H_S2]
    vd_app = x[X_VD_APP]
    vq_app = x[X_VQ_APP]
    ihat_d = x[X_IHAT_D]
    ihat_q = x[X_IHAT_Q]

    # ZOH matrices of the true plant and of the nominal model (decoupling), cached per w_e
    w_zoh = n_p * w_m
    a00, a01, a10, a11, b00, b01, b10, b11 = zoh_dq(r, ld, lq, w_zoh, ts)
    c00, c01, c10, c11, e00, e01, e10, e11 = zoh_dq(p[P_R_NOM], ld_nom, lq_nom, w_zoh, ts)
    s_ud = 0.0
    s_uq = 0.0
    s_te = 0.0
    s_w = 0.0
    s_tl = 0.0
    n_over = 0
    for k in range(n):
        w_e = n_p * w_m
        # ---------------- firmware: current control at sample k ----------------
        if power:
            id_fb = i_d
            iq_fb = i_q
            if decouple:
                id_fb -= ihat_d
                iq_fb -= ihat_q
            e_d = id_ref - id_fb
            e_q = iq_ref - iq_fb
            u_d = p[P_KP_D] * e_d + int_d - w_e * lq_nom * iq_ref
            u_q = p[P_KP_Q] * e_q + int_q + w_e * (ld_nom * id_ref + psi_nom)
            mag = math.sqrt(u_d * u_d + u_q * u_q)
            if mag > u_lim:
                scale = u_lim / mag if mag > 0.0 else 0.0
                u_d *= scale
                u_q *= scale
            else:
                int_d += p[P_KI_D] * ts * e_d
                int_q += p[P_KI_Q] * ts * e_q
            if inject:
                v_inj = th_c * math.cos(h * phi) + th_s * math.sin(h * phi)
                # (numba fuses the cos/sin pair of one argument)
                cv = math.cos(v_inj)
                sv = math.sin(v_inj)
                u_ds = u_d * cv - u_q * sv
                u_qs = u_d * sv + u_q * cv
            else:
                v_inj = 0.0
                u_ds = u_d
                u_qs = u_q
        else:
            u_d = 0.0
            u_q = 0.0
            u_ds = 0.0
            u_qs = 0.0
            v_inj = 0.0
            int_d = 0.0
            int_q = 0.0
        # firmware torque estimate (0x6077) from measured currents and nominal parameters
        te_est = k_t_nom * i_q + 1.5 * n_p * (ld_nom - lq_nom) * i_d * i_q

        # ---------------- plant: torque, shaft, sensor at sample k ----------------
        dist = 0.0
        if d_amp != 0.0:
            # cos(x + phi_D) and cos(2x + phi_D2) from one cos/sin pair of x = h phi_e
            cx = math.cos(h_dist * phi)
            sx = math.sin(h_dist * phi)
            c2x = 2.0 * cx * cx - 1.0
            s2x = 2.0 * sx * cx
            dist = (d_amp * (cx * cos_pd - sx * sin_pd)
                    + d2_amp * (c2x * cos_pd2 - s2x * sin_pd2))
        t_em = 1.5 * n_p * (psi * i_q + (ld - lq) * i_d * i_q) + dist
        # load machine: ramped reference, PI speed loop (bumpless when switched on)
        if load_on:
            ref_prev = load_ref
            if load_ref < load_target - ramp:
                load_ref += ramp
            elif load_ref > load_target + ramp:
                load_ref -= ramp
            else:
                load_ref = load_target
            e_w = load_ref - w_m
            # acceleration feed-forward J dref/dt: the ramp needs no integrator wind-up (no overshoot)
            t_lm = p[P_LOAD_KP] * e_w + load_int + p[P_J] * (load_ref - ref_prev) / ts
            if t_lm > tmax:
                t_lm = tmax
            elif t_lm < -tmax:
                t_lm = -tmax
            else:
                load_int += p[P_LOAD_KI] * ts * e_w
        else:
            load_ref = w_m
            load_int = 0.0
            t_lm = 0.0
        alpha = (t_em + t_lm - p[P_B] * w_m) / p[P_J]
        # accelerometer path H(z), direct form II transposed
        y = b0 * alpha + hs1
        hs1 = b1 * alpha - a1 * y + hs2
        hs2 = b2 * alpha - a2 * y
        a_meas = y + sigma * noise[k]
        raw = a_meas / fs * 32767.0
        fl = sync_bits
        if raw > 32767.0:
            raw = 32767.0
            fl |= OVER_RANGE_FLAG
            n_over += 1
        elif raw < -32767.0:
            raw = -32767.0
            fl |= OVER_RANGE_FLAG
            n_over += 1
        accel_counts[k] = np.int16(round(raw))
        angle_counts[k] = np.uint16(int(phi * counts_per_rad + 0.5) & 0xFFFF)
        flags[k] = np.uint16(fl)

        if record:
            trace[k, TR_ID] = i_d
            trace[k, TR_IQ] = i_q
            trace[k, TR_UD] = u_d
            trace[k, TR_UQ] = u_q
            trace[k, TR_UD_STAR] = u_ds
            trace[k, TR_UQ_STAR] = u_qs
            trace[k, TR_TORQUE] = t_em
            trace[k, TR_DIST] = dist
            trace[k, TR_ALPHA] = alpha
            trace[k, TR_ALPHA_MEAS] = a_meas
            trace[k, TR_PHI_E] = phi
            trace[k, TR_OMEGA_M] = w_m
            trace[k, TR_V_INJ] = v_inj
            trace[k, TR_T_LOAD] = t_lm
        s_ud += u_d
        s_uq += u_q
        s_te += te_est
        s_w += w_m
        s_tl += t_lm

        # ---------------- advance to k+1 ----------------
        if power:
            if abs(w_e - w_zoh) > OMEGA_RECOMPUTE_RAD_S:
                # the exponential depends on w_e only; a 1e-3 rad/s step changes the cross-coupling
                # voltage by ~1e-6 relative, so recomputing on change is as good as every period
                a00, a01, a10, a11, b00, b01, b10, b11 = zoh_dq(r, ld, lq, w_e, ts)
                if decouple:
                    c00, c01, c10, c11, e00, e01, e10, e11 = zoh_dq(p[P_R_NOM], ld_nom, lq_nom, w_e, ts)
                w_zoh = w_e
            ue_d = ud_app
            ue_q = uq_app - w_e * psi
            i_d_new = a00 * i_d + a01 * i_q + b00 * ue_d + b01 * ue_q
            i_q_new = a10 * i_d + a11 * i_q + b10 * ue_d + b11 * ue_q
            i_d = i_d_new
            i_q = i_q_new
            if decouple:
                # nominal model of the currents the applied injection voltage causes (section 3.1)
                hd = c00 * ihat_d + c01 * ihat_q + e00 * vd_app + e01 * vq_app
                hq = c10 * ihat_d + c11 * ihat_q + e10 * vd_app + e11 * vq_app
                ihat_d = hd
                ihat_q = hq
            else:
                ihat_d = 0.0
                ihat_q = 0.0
            ud_app = u_ds
            uq_app = u_qs
            vd_app = u_ds - u_d
            vq_app = u_qs - u_q
        else:
            # inverter off: the currents commutate into the DC link through the diodes and die out
            i_d *= p[P_OFF_DECAY]
            i_q *= p[P_OFF_DECAY]
            ud_app = 0.0
            uq_app = 0.0
            vd_app = 0.0
            vq_app = 0.0
            ihat_d = 0.0
            ihat_q = 0.0
        w_new = w_m + ts * alpha
        phi += n_p * ts * 0.5 * (w_m + w_new)
        phi = phi % TWO_PI
        w_m = w_new

    x[X_ID] = i_d
    x[X_IQ] = i_q
    x[X_UD_APP] = ud_app
    x[X_UQ_APP] = uq_app
    x[X_INT_D] = int_d
    x[X_INT_Q] = int_q
    x[X_PHI_E] = phi
    x[X_OMEGA_M] = w_m
    x[X_LOAD_INT] = load_int
    x[X_LOAD_REF] = load_ref
    x[X_H_S1] = hs1
    x[X_H_S2] = hs2
    x[X_VD_APP] = vd_app
    x[X_VQ_APP] = vq_app
    x[X_IHAT_D] = ihat_d
    x[X_IHAT_Q] = ihat_q
    x[X_SAMPLES] += n
    summary[Y_UD_SUM] = s_ud
    summary[Y_UQ_SUM] = s_uq
    summary[Y_TORQUE_EST_SUM] = s_te
    summary[Y_OMEGA_SUM] = s_w
    summary[Y_LOAD_TORQUE_SUM] = s_tl
    summary[Y_OVER_RANGE] = n_over


# ------------------------------------------------------------------------------------------------
# Python-side helpers (startup only)


def sensor_biquad(zero_rad_s: float, pole_re_rad_s: float, pole_im_rad_s: float, ts_s: float):
    """H(s) = J G_Salpha(s) = (w0^2/(-z)) (s - z)/((s - p1)(s - p2)), w0 = |p|, so H(0) = 1
    (section 2.3: z = -35954, p = -19.6 +- j6746.2 rad/s). Bilinear transform pre-warped at w0 so
    the lightly damped resonance lands at the right frequency. Returns (b0, b1, b2, a1, a2)."""
    from scipy.signal import bilinear

    w0_sq = pole_re_rad_s ** 2 + pole_im_rad_s ** 2
    w0 = math.sqrt(w0_sq)
    num = np.array([1.0, -zero_rad_s]) * (w0_sq / (-zero_rad_s))
    den = np.array([1.0, -2.0 * pole_re_rad_s, w0_sq])
    # pre-warping: bilinear with the sample rate that maps w0 exactly
    fs_warp = w0 / (2.0 * math.tan(w0 * ts_s / 2.0))
    bz, az = bilinear(num, den, fs=fs_warp)
    bz = np.concatenate([bz, np.zeros(3 - len(bz))]) / az[0]
    az = az / az[0]
    return float(bz[0]), float(bz[1]), float(bz[2]), float(az[1]), float(az[2])


def sensor_response(p: np.ndarray, omega_rad_s: float) -> complex:
    """Frequency response of the discrete sensor path H(e^{j w T_s}) (for tests / calibration)."""
    z = np.exp(1j * omega_rad_s * p[P_TS])
    num = p[P_H_B0] + p[P_H_B1] / z + p[P_H_B2] / z ** 2
    den = 1.0 + p[P_H_A1] / z + p[P_H_A2] / z ** 2
    return complex(num / den)


def new_state() -> np.ndarray:
    return np.zeros(N_STATE)


def new_setpoints(udc_v: float = 0.0) -> np.ndarray:
    sp = np.zeros(N_SETPOINTS)
    sp[S_H] = 6.0
    sp[S_UDC_V] = udc_v
    return sp


def steady_state_init(x: np.ndarray, p: np.ndarray, torque_nm: float, speed_rpm: float,
                      udc_v: float) -> None:
    """Put the state at the analytic dq steady state of an operating point (no injection, no d):
    i_d = 0, i_q = T*/(1.5 N_p psi_nom), integrators at the resistive drop, shaft at speed with the
    load machine holding it. Saves simulated settling time in tests and calibration."""
    w_m = speed_rpm * TWO_PI / 60.0
    w_e = p[P_NP] * w_m
    _, iq = torque_to_current_ref(torque_nm, p[P_PSI_NOM], p[P_NP], p[P_IMAX])
    x[:] = 0.0
    x[X_IQ] = iq
    x[X_OMEGA_M] = w_m
    x[X_LOAD_REF] = w_m
    # true steady voltage: u_d = -w_e L_q i_q, u_q = R i_q + w_e psi; PI integrators hold the rest
    ud = -w_e * p[P_LQ] * iq
    uq = p[P_R] * iq + w_e * p[P_PSI]
    x[X_UD_APP] = ud
    x[X_UQ_APP] = uq
    x[X_INT_D] = ud - (-w_e * p[P_LQ_NOM] * iq)
    x[X_INT_Q] = uq - w_e * p[P_PSI_NOM]
    t_em = 1.5 * p[P_NP] * p[P_PSI] * iq
    x[X_LOAD_INT] = -t_em + p[P_B] * w_m


class Plant:
    """Stateful convenience wrapper around `simulate_chunk` (used by the process and by tests)."""

    def __init__(self, params: np.ndarray, noise_seed: int | None = 0):
        self.p = np.asarray(params, dtype=np.float64).copy()
        self.x = new_state()
        self.rng = np.random.default_rng(noise_seed)
        self.summary = np.zeros(N_SUMMARY)
        self._no_trace = np.zeros((0, N_TRACE))

    def run(self, sp: np.ndarray, n: int, trace: bool = False):
        """Simulate n samples with setpoints sp. Returns (angle_counts, accel_counts, flags, trace)."""
        noise = self.rng.standard_normal(n) if self.p[P_NOISE] > 0.0 else np.zeros(n)
        angle = np.empty(n, dtype=np.uint16)
        accel = np.empty(n, dtype=np.int16)
        flags = np.empty(n, dtype=np.uint16)
        tr = np.zeros((n, N_TRACE)) if trace else self._no_trace
        simulate_chunk(self.x, self.p, np.asarray(sp, dtype=np.float64), noise, angle, accel, flags,
                       self.summary, tr)
        return angle, accel, flags, (tr if trace else None)
