"""Physics of the emulated bench at the controller rate: pure functions over state arrays.

One call of `simulate` advances drive firmware control loop + inverter + PMSM + shaft + load machine
+ accelerometer + DAQ framing by n control periods T_s (1/16 kHz in paper-bench), in chunks of
`chunk` samples (setpoints are constant over a call; the chunk-rate firmware tasks run at every chunk
start). Everything is in SI units (V, A, Ohm, H, Wb, Nm, rad, rad/s, rad/s^2, kg m^2); no CAN, no pty,
no threads here, so tests run the physics directly. The state lives in flat float64 arrays indexed
by the X_*/P_*/S_* constants below (numba compiles them as constants); the scenario's tables
(saturation, disturbance map) live in one flat array `tab` whose offsets are in `p`.

Chunk-rate firmware task (every `chunk` samples, like a real drive's 1 kHz torque task):
  torque -> current references from the NOMINAL parameters ([firmware]) (feed-forward): MTPA (i_d = 0 for
  L_d = L_q, else the MTPA curve), and above the voltage limit field weakening: i_d < 0 such that
  the nominal steady-state |u_dq| = margin * U_dc/sqrt(3) (on the side of the constant-torque curve
  nearer MTPA); current limit I_max (i_d has priority). Per period, a slow voltage loop (as drives do to
  survive parameter errors) adds delta i_d <= 0 while the PI output |u| exceeds fw_target U_dc/sqrt(3):
  d(delta i_d)/dt = -w_fw (|u| - u_target) / (|w_e| L_d,nom), i_q cut to the current limit.
Per control period k (paper section 2, Fig. 3):
  PI         u = K_p e + integral + feed-forward of back-EMF and cross coupling computed from the
             REFERENCES (not the measured currents), |u| <= U_dc/sqrt(3) (vector scaling,
             conditional-integration anti-windup). K_p = 2 pi f_bw L_nom, K_i = 2 pi f_bw R_nom.
  injection  v_inj = theta_cos cos(h phi_e) + theta_sin sin(h phi_e)            (eq. 3, 12)
             default: u* = R(v_inj) u (exact rotation, |u*| = |u|, eq. 2-4);
             eq. 11 variant (S_VEST): u* = u + (R(v_inj) - I) u_hat0, u_hat0 = sat(G_EM^-1 G_cl i*)
             from the nominal model (the injection no longer follows the PI output's harmonics).
  decoupl.   (S_DECOUPLING, section 3.1) the harmonic currents the applied injection voltage u* - u
             causes are estimated with the nominal model and subtracted from the measured currents.
  delay      u*(k) is applied during period k+1 (one period computation + ZOH = 1.5 T_s, Table 1).
             The firmware's inverse Park uses the angle advanced to the middle of that period (P_ANGLE_COMP,
             standard practice); the inverter holds the alpha-beta vector over the period, so the dq
             average is u* sinc(w_e T_s/2) (and rotated by -1.5 w_e T_s without angle compensation).
  inverter   dead time: per phase x the voltage error -U_dc T_dead f_pwm sgn(i_x), averaged over the
             period (sgn linear within the larger of +-i_zc and half the current change per period),
             transformed to dq with the electrical angle: its own 6k harmonics.
  PMSM       L_d di_d/dt = u_d - R i_d + w_e L_q i_q
             L_q di_q/dt = u_q - R i_q - w_e (L_d i_d + psi_p)                   (eq. 18, 19)
             exact ZOH discretisation with the 2x2 matrix exponential at w_e; L_d, L_q, psi_p from the
             saturation tables at the (1 ms low-pass filtered) current magnitude, updated per chunk.
  torque     T_em = 1.5 N_p (psi_p i_q + (L_d - L_q) i_d i_q) + d                (eq. 20 plus d)
             d = D cos(h phi_e + phi_D) + r D cos(2 h phi_e + phi_D2); D, phi_D bilinear in the
             disturbance map over (T*, speed), interpolated as the phasor (D cos phi_D, D sin phi_D).
  shaft      J dw_m/dt = T_em + T_lm - B w_m  (T_lm: load machine torque: ramped speed reference,
             PI speed loop plus acceleration feed-forward)
  sensor     alpha_meas = H(z) dw_m/dt + noise, H = J G_Salpha (zero z, poles p, H(0) = 1,
             section 2.3), bilinear with pre-warping at |p|; int16 counts of the full scale.
  DAQ        12-byte frames (DESIGN 5) written straight into a byte buffer, CRC-16/CCITT-FALSE.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from drivers.daq_protocol import CRC_TABLE, FLAG_OVER_RANGE, FLAG_SYNC_INPUT, FRAME_BYTES, FRAME_DTYPE

SQRT3 = math.sqrt(3.0)
TWO_PI = 2.0 * math.pi

# ---- parameter vector (truth, firmware nominal, sensor, load, inverter, table offsets) ----
P_TS = 0            # s, control period
P_NP = 1            # pole pairs
P_R = 2             # Ohm, true stator resistance
P_LD = 3            # H, true L_d at zero current (times the saturation table factor)
P_LQ = 4            # H
P_PSI = 5           # Wb, true PM flux linkage at zero current (times the table factor)
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
P_DIST_SCALE = 24   # factor on the whole disturbance map (1; tests/calibration set 0)
P_D2_RATIO = 27     # D_2 / D
P_PHI_D2 = 28       # rad
P_T_RATED = 29      # Nm
P_H_DIST = 30       # order of the true torque harmonic
P_LOAD_KP = 31      # Nm/(rad/s)
P_LOAD_KI = 32      # Nm/rad
P_LOAD_RAMP = 33    # rad/s^2 (mechanical), ramp of the speed reference
P_LOAD_TMAX = 34    # Nm
P_OFF_DECAY = 35    # per-period factor of the currents with the inverter off
P_T_DEAD = 36       # s, inverter dead time (0: off)
P_F_PWM = 37        # Hz, PWM frequency
P_I_ZC = 38         # A, dead-time sign(i) is linear within +-i_zc
P_V_MARGIN = 39     # field weakening targets margin * U_dc/sqrt(3)
P_ANGLE_COMP = 40   # 1: inverse Park with the angle advanced by 1.5 w_e T_s
P_W_BW = 41         # rad/s, nominal current-loop bandwidth (G_cl of eq. 11)
P_SAT_DECAY = 42    # per-period factor of the |i| low-pass that drives the saturation tables
P_SAT_N = 43        # number of points of the saturation tables
P_SAT_OFF = 44      # offset of [i_axis, ld_rel, lq_rel, psi_rel] in tab
P_DMAP_NT = 45      # disturbance map: torque axis length
P_DMAP_NN = 46      # speed axis length
P_DMAP_OFF = 47     # offset of [torque axis, speed axis (rad/s mech), X (nn*nt), Y (nn*nt)] in tab
P_FW_BW = 48        # rad/s, bandwidth of the closed-loop field weakening (0: feed-forward only)
P_FW_TARGET = 49    # the voltage loop holds |u| <= target * U_dc/sqrt(3)
N_PARAMS = 50

# ---- setpoints, constant over one call (applied at its first sample) ----
S_POWER = 0         # 1: power stage on (OPERATION_ENABLED and DC link ok)
S_TORQUE_NM = 1     # torque command T*
S_THETA_COS = 2     # rad, already clamped and zero when injection is off
S_THETA_SIN = 3
S_H = 4             # harmonic order used by the firmware's injection
S_DECOUPLING = 5    # 0/1
S_UDC_V = 6         # DC-link voltage
S_LOAD_ON = 7       # 1: load machine speed loop active
S_LOAD_SPEED = 8    # rad/s, mechanical target speed of the load machine
S_SYNC = 9          # 0/1, level of the DAQ sync flag during this call
S_VEST = 10         # 0/1, eq. 11: G_comp from the estimate u_hat_dq,0 instead of the PI output
N_SETPOINTS = 11

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
X_IMAG_F = 17       # A, low-pass filtered current magnitude (saturation)
X_IF_D = 18         # A, eq. 11: i* through the nominal closed loop G_cl
X_IF_Q = 19
X_FW_DID = 20       # A, closed-loop field weakening: i_d correction (<= 0)
N_STATE = 21

# ---- per-chunk summary (rows of summary[n_chunks, N_SUMMARY]) ----
Y_UD_SUM = 0        # sum of nominal u_d over the chunk (V)
Y_UQ_SUM = 1
Y_TORQUE_EST_SUM = 2  # firmware torque estimate from measured currents, nominal params (Nm)
Y_OMEGA_SUM = 3
Y_LOAD_TORQUE_SUM = 4
Y_OVER_RANGE = 5    # count of clipped samples
Y_ID_REF = 6        # current references of the chunk (A)
Y_IQ_REF = 7
N_SUMMARY = 8

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
TR_UD_DT = 14       # dead-time voltage error in dq (applied with u*)
TR_UQ_DT = 15
N_TRACE = 16

OMEGA_RECOMPUTE_RAD_S = 0.05  # electrical rad/s change that triggers a new matrix exponential
SYNC_FLAG = FLAG_SYNC_INPUT
OVER_RANGE_FLAG = FLAG_OVER_RANGE


# ------------------------------------------------------------------------------------------------
# firmware: torque -> current references (nominal parameters)


@njit(cache=True)
def _torque_of(i_d, i_q, psi, ld, lq, n_p):
    return 1.5 * n_p * (psi * i_q + (ld - lq) * i_d * i_q)


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
            if (_u_mag(m1, _iq_for_torque(t, m1, psi, ld, lq, n_p), aw, r, ld, lq, psi)
                    < _u_mag(m2, _iq_for_torque(t, m2, psi, ld, lq, n_p), aw, r, ld, lq, psi)):
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


@njit(cache=True)
def torque_to_current_ref(torque_nm, psi_nom_wb, n_p, i_max_a):
    """Surface-magnet MTPA below base speed: i_d* = 0, i_q* = T*/(1.5 N_p psi_p) (kept for callers)."""
    return current_reference(torque_nm, 0.0, 0.0, 0.0, 1.0, 1.0, psi_nom_wb, n_p, i_max_a, 1.0)


# ------------------------------------------------------------------------------------------------
# plant helpers


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
def _cpow(c, s, n):
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
def _crc_byte(crc, byte):
    return ((crc << 8) & 0xFFFF) ^ CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]


@njit(cache=True, inline="always")
def _store_chunk_sums(summary, row, s_ud, s_uq, s_te, s_w, s_tl, n_over):
    """The per-chunk sums of one finished chunk into its summary row."""
    summary[row, Y_UD_SUM] = s_ud
    summary[row, Y_UQ_SUM] = s_uq
    summary[row, Y_TORQUE_EST_SUM] = s_te
    summary[row, Y_OMEGA_SUM] = s_w
    summary[row, Y_LOAD_TORQUE_SUM] = s_tl
    summary[row, Y_OVER_RANGE] = n_over


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
def disturbance_phasor(p, tab, torque_nm, w_m):
    """(X, Y) = (D cos phi_D, D sin phi_D) of the h-th torque harmonic at (T*, w_m), bilinear."""
    nt = int(p[P_DMAP_NT])
    nn = int(p[P_DMAP_NN])
    if nt == 0 or nn == 0:
        return 0.0, 0.0
    off = int(p[P_DMAP_OFF])
    jt, ft = _axis_pos(tab, off, nt, torque_nm)
    jn, fn = _axis_pos(tab, off + nt, nn, w_m)
    xo = off + nt + nn
    yo = xo + nt * nn
    jt1 = jt + 1 if nt > 1 else jt
    jn1 = jn + 1 if nn > 1 else jn
    w00 = (1.0 - ft) * (1.0 - fn)
    w01 = ft * (1.0 - fn)
    w10 = (1.0 - ft) * fn
    w11 = ft * fn
    x = (w00 * tab[xo + jn * nt + jt] + w01 * tab[xo + jn * nt + jt1]
         + w10 * tab[xo + jn1 * nt + jt] + w11 * tab[xo + jn1 * nt + jt1])
    y = (w00 * tab[yo + jn * nt + jt] + w01 * tab[yo + jn * nt + jt1]
         + w10 * tab[yo + jn1 * nt + jt] + w11 * tab[yo + jn1 * nt + jt1])
    s = p[P_DIST_SCALE]
    return s * x, s * y


@njit(cache=True)
def saturated_params(p, tab, i_mag):
    """True (L_d, L_q, psi_p) at a current magnitude: base values times the table factors."""
    n = int(p[P_SAT_N])
    if n == 0:
        return p[P_LD], p[P_LQ], p[P_PSI]
    off = int(p[P_SAT_OFF])
    return (p[P_LD] * _interp_tab(tab, off, n, 1, i_mag), p[P_LQ] * _interp_tab(tab, off, n, 2, i_mag),
            p[P_PSI] * _interp_tab(tab, off, n, 3, i_mag))


# ------------------------------------------------------------------------------------------------
# the control period loop


@njit(cache=True, nogil=True)
def simulate(x, p, tab, sp, noise, chunk, seq0, frames, summary, trace):
    """Advance the bench by n = len(noise) control periods in place.

    x: state (N_STATE), p: parameters (N_PARAMS), tab: tables, sp: setpoints (N_SETPOINTS), noise: n
    standard normal samples for the sensor. frames: uint8 array of 12 n bytes receiving the DAQ frames
    (sequence numbers from seq0), or an empty array to skip. summary: (ceil(n / chunk), N_SUMMARY) sums
    per chunk. trace: (n, N_TRACE) array filled per sample, or shape (0, N_TRACE) to skip recording.
    """
    n = noise.shape[0]
    record = trace.shape[0] >= n
    write_frames = frames.shape[0] >= n * FRAME_BYTES
    ts = p[P_TS]
    n_p = p[P_NP]
    r = p[P_R]
    r_nom = p[P_R_NOM]
    ld_nom = p[P_LD_NOM]
    lq_nom = p[P_LQ_NOM]
    psi_nom = p[P_PSI_NOM]
    k_t_nom = 1.5 * n_p * psi_nom
    kp_d = p[P_KP_D]
    kp_q = p[P_KP_Q]
    ki_d = p[P_KI_D] * ts
    ki_q = p[P_KI_Q] * ts
    power = sp[S_POWER] > 0.5
    torque_ref = sp[S_TORQUE_NM] if power else 0.0
    th_c = sp[S_THETA_COS]
    th_s = sp[S_THETA_SIN]
    inject = th_c != 0.0 or th_s != 0.0
    h_int = int(sp[S_H] + 0.5)
    decouple = sp[S_DECOUPLING] > 0.5
    vest = sp[S_VEST] > 0.5
    udc = sp[S_UDC_V]
    u_lim = udc / SQRT3
    load_on = sp[S_LOAD_ON] > 0.5
    load_target = sp[S_LOAD_SPEED]
    sync_bits = SYNC_FLAG if sp[S_SYNC] > 0.5 else 0
    d2_ratio = p[P_D2_RATIO]
    h_dist_int = int(p[P_H_DIST] + 0.5)
    same_h = h_dist_int == h_int
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
    # dead time: amplitude of the per-phase voltage error, smoothing of sgn(i)
    dt_amp = udc * p[P_T_DEAD] * p[P_F_PWM]
    dead_time = dt_amp > 0.0 and power
    inv_izc = 1.0 / p[P_I_ZC] if p[P_I_ZC] > 0.0 else 1e12
    angle_comp = p[P_ANGLE_COMP] > 0.5
    # eq. 11 filter: G_cl first order at w_bw, exact discretisation
    w_bw = p[P_W_BW]
    g_cl = 1.0 - math.exp(-w_bw * ts)
    sat_decay = p[P_SAT_DECAY]
    u_fw_target = p[P_FW_TARGET] * u_lim
    i_max2 = p[P_IMAX] * p[P_IMAX]

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
    imag_f = x[X_IMAG_F]
    if_d = x[X_IF_D]
    if_q = x[X_IF_Q]
    fw_did = x[X_FW_DID]
    seq = seq0
    id_ff = 0.0
    iq_ff = 0.0
    fw_gain = 0.0
    fw_did_min = 0.0

    # chunk-rate quantities (set at k % chunk == 0)
    id_ref = 0.0
    iq_ref = 0.0
    ld = p[P_LD]
    lq = p[P_LQ]
    psi = p[P_PSI]
    d_x = 0.0
    d_y = 0.0
    d_on = False
    w_zoh = 0.0
    a00 = a01 = a10 = a11 = b00 = b01 = b10 = b11 = 0.0
    c00 = c01 = c10 = c11 = e00 = e01 = e10 = e11 = 0.0
    app_c = 1.0     # inverter: dq average of the applied voltage = u* (app_c + j app_s)
    app_s = 0.0
    rot_c = 1.0     # rotation by half a period (dead-time error at the middle of the period)
    rot_s = 0.0
    s_ud = s_uq = s_te = s_w = s_tl = 0.0
    n_over = 0
    countdown = 0
    for k in range(n):
        w_e = n_p * w_m
        if countdown == 0:
            countdown = chunk
            # ---------------- chunk-rate firmware task and slow plant parameters ----------------
            if power:
                id_ff, iq_ff = current_reference(torque_ref, w_e, udc, r_nom, ld_nom, lq_nom, psi_nom, n_p,
                                                 p[P_IMAX], p[P_V_MARGIN])
            else:
                id_ff = 0.0
                iq_ff = 0.0
                fw_did = 0.0
            id_ref = id_ff + fw_did
            iq_ref = iq_ff
            aw_l = abs(w_e) * ld_nom
            fw_gain = p[P_FW_BW] * ts / aw_l if (aw_l > 0.0 and power) else 0.0
            fw_did_min = -p[P_IMAX] - id_ff
            ld, lq, psi = saturated_params(p, tab, imag_f)
            d_x, d_y = disturbance_phasor(p, tab, torque_ref, w_m)
            d_on = d_x != 0.0 or d_y != 0.0
            a00, a01, a10, a11, b00, b01, b10, b11 = zoh_dq(r, ld, lq, w_e, ts)
            c00, c01, c10, c11, e00, e01, e10, e11 = zoh_dq(r_nom, ld_nom, lq_nom, w_e, ts)
            w_zoh = w_e
            half = 0.5 * w_e * ts
            sinc = math.sin(half) / half if abs(half) > 1e-9 else 1.0
            rho = 0.0 if angle_comp else -3.0 * half
            app_c = sinc * math.cos(rho)
            app_s = sinc * math.sin(rho)
            rot_c = math.cos(half)
            rot_s = math.sin(half)
            if k > 0:
                _store_chunk_sums(summary, k // chunk - 1, s_ud, s_uq, s_te, s_w, s_tl, n_over)
            summary[k // chunk, Y_ID_REF] = id_ref
            summary[k // chunk, Y_IQ_REF] = iq_ref
            s_ud = s_uq = s_te = s_w = s_tl = 0.0
            n_over = 0
        countdown -= 1
        cphi = math.cos(phi)
        sphi = math.sin(phi)
        # cos/sin of h phi_e (injection) and of the disturbance order, from cos/sin phi_e
        chp, shp = _cpow(cphi, sphi, h_int)
        # ---------------- firmware: current control at sample k ----------------
        if power:
            id_fb = i_d
            iq_fb = i_q
            if decouple:
                id_fb -= ihat_d
                iq_fb -= ihat_q
            e_d = id_ref - id_fb
            e_q = iq_ref - iq_fb
            # feed-forward of cross coupling and back-EMF from the references (see module doc)
            u_d = kp_d * e_d + int_d - w_e * lq_nom * iq_ref
            u_q = kp_q * e_q + int_q + w_e * (ld_nom * id_ref + psi_nom)
            mag = math.sqrt(u_d * u_d + u_q * u_q)
            if fw_gain > 0.0:
                # closed-loop field weakening on the PI output magnitude (integrator clamped to <= 0)
                fw_did -= fw_gain * (mag - u_fw_target)
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
            if mag > u_lim:
                scale = u_lim / mag if mag > 0.0 else 0.0
                u_d *= scale
                u_q *= scale
            else:
                int_d += ki_d * e_d
                int_q += ki_q * e_q
            if vest:
                # eq. 11: u_hat0 = sat(G_EM^-1 G_cl i*), nominal model, G_cl first order at w_bw
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
            else:
                uh_d = u_d
                uh_q = u_q
                if_d = id_ref
                if_q = iq_ref
            if inject:
                v_inj = th_c * chp + th_s * shp
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
            if_d = 0.0
            if_q = 0.0
        # firmware torque estimate (0x6077) from measured currents and nominal parameters
        te_est = k_t_nom * i_q + 1.5 * n_p * (ld_nom - lq_nom) * i_d * i_q

        # ---------------- plant: torque, shaft, sensor at sample k ----------------
        dist = 0.0
        if d_on:
            if same_h:
                cx = chp
                sx = shp
            else:
                cx, sx = _cpow(cphi, sphi, h_dist_int)
            c2x = 2.0 * cx * cx - 1.0
            s2x = 2.0 * sx * cx
            # D cos(x + phi_D) = X cos x - Y sin x; 2h part with |D| r at phi_D2
            dist = d_x * cx - d_y * sx
            if d2_ratio != 0.0:
                d2 = d2_ratio * math.sqrt(d_x * d_x + d_y * d_y)
                dist += d2 * (c2x * cos_pd2 - s2x * sin_pd2)
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
        if write_frames:
            # round half away from zero (int16 counts), angle counts modulo 65536
            acc = (int(raw + 0.5) if raw >= 0.0 else -int(-raw + 0.5)) & 0xFFFF
            ang = int(phi * counts_per_rad + 0.5) & 0xFFFF
            sq = seq & 0xFFFF
            o = k * FRAME_BYTES
            crc = _crc_byte(0xFFFF, sq & 0xFF)
            crc = _crc_byte(crc, sq >> 8)
            crc = _crc_byte(crc, ang & 0xFF)
            crc = _crc_byte(crc, ang >> 8)
            crc = _crc_byte(crc, acc & 0xFF)
            crc = _crc_byte(crc, acc >> 8)
            crc = _crc_byte(crc, fl & 0xFF)
            crc = _crc_byte(crc, fl >> 8)
            frames[o] = 0xA5
            frames[o + 1] = 0x5A
            frames[o + 2] = sq & 0xFF
            frames[o + 3] = sq >> 8
            frames[o + 4] = ang & 0xFF
            frames[o + 5] = ang >> 8
            frames[o + 6] = acc & 0xFF
            frames[o + 7] = acc >> 8
            frames[o + 8] = fl & 0xFF
            frames[o + 9] = fl >> 8
            frames[o + 10] = crc & 0xFF
            frames[o + 11] = crc >> 8
            seq += 1

        # ---------------- inverter: dead-time error over the next period ----------------
        ed = 0.0
        eq = 0.0
        if dead_time:
            # period average of -dt_amp sgn(i_x(t)) for each phase: the phase currents at the middle of
            # the period (dq current at the mid-period angle), sgn linear within the half change of
            # the current over the period (exact average for a current crossing zero linearly) or
            # the zero-current band, whichever is wider. Evaluating sgn only at the sample instants
            # instead would tie the crossings to the sample grid (120 samples per period at 2000 rpm).
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
            ed = e_al * cm + e_be * sm
            eq = -e_al * sm + e_be * cm

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
            trace[k, TR_UD_DT] = ed
            trace[k, TR_UQ_DT] = eq
        s_ud += u_d
        s_uq += u_q
        s_te += te_est
        s_w += w_m
        s_tl += t_lm

        # ---------------- advance to k+1 ----------------
        if power:
            if abs(w_e - w_zoh) > OMEGA_RECOMPUTE_RAD_S:
                # the exponential depends on w_e only; a 0.05 rad/s step changes the cross-coupling
                # voltage by ~1e-4 V at I_max, so recomputing on change is as good as every period
                a00, a01, a10, a11, b00, b01, b10, b11 = zoh_dq(r, ld, lq, w_e, ts)
                if decouple:
                    c00, c01, c10, c11, e00, e01, e10, e11 = zoh_dq(r_nom, ld_nom, lq_nom, w_e, ts)
                w_zoh = w_e
            ue_d = ud_app * app_c - uq_app * app_s + ed
            ue_q = ud_app * app_s + uq_app * app_c + eq - w_e * psi
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
        imag_f = sat_decay * imag_f + (1.0 - sat_decay) * math.sqrt(i_d * i_d + i_q * i_q)
        w_new = w_m + ts * alpha
        phi += n_p * ts * 0.5 * (w_m + w_new)
        if phi >= TWO_PI:
            phi -= TWO_PI
        elif phi < 0.0:
            phi += TWO_PI
        w_m = w_new

    if n > 0:
        _store_chunk_sums(summary, (n - 1) // chunk, s_ud, s_uq, s_te, s_w, s_tl, n_over)
    x[X_ID] = i_d
    x[X_IQ] = i_q
    x[X_UD_APP] = ud_app
    x[X_UQ_APP] = uq_app
    x[X_INT_D] = int_d
    x[X_INT_Q] = int_q
    x[X_PHI_E] = phi % TWO_PI
    x[X_OMEGA_M] = w_m
    x[X_LOAD_INT] = load_int
    x[X_LOAD_REF] = load_ref
    x[X_H_S1] = hs1
    x[X_H_S2] = hs2
    x[X_VD_APP] = vd_app
    x[X_VQ_APP] = vq_app
    x[X_IHAT_D] = ihat_d
    x[X_IHAT_Q] = ihat_q
    x[X_IMAG_F] = imag_f
    x[X_IF_D] = if_d
    x[X_IF_Q] = if_q
    x[X_FW_DID] = fw_did
    x[X_SAMPLES] += n


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
                      udc_v: float, tab: np.ndarray | None = None) -> None:
    """Put the state near the steady state of an operating point (no injection, no d, no dead time):
    the firmware's current references, integrators at what the true machine needs beyond the
    feed-forward, shaft at speed with the load machine holding it. Saves settling time in tests and
    calibration (the remaining transient, e.g. the dead-time voltage, settles within ~10 ms)."""
    w_m = speed_rpm * TWO_PI / 60.0
    w_e = p[P_NP] * w_m
    i_d, i_q = current_reference(torque_nm, w_e, udc_v, p[P_R_NOM], p[P_LD_NOM], p[P_LQ_NOM], p[P_PSI_NOM],
                                 p[P_NP], p[P_IMAX], p[P_V_MARGIN])
    ld, lq, psi = p[P_LD], p[P_LQ], p[P_PSI]
    if tab is not None:
        ld, lq, psi = saturated_params(p, tab, math.hypot(i_d, i_q))
    x[:] = 0.0
    x[X_ID] = i_d
    x[X_IQ] = i_q
    x[X_OMEGA_M] = w_m
    x[X_LOAD_REF] = w_m
    x[X_IMAG_F] = math.hypot(i_d, i_q)
    x[X_IF_D] = i_d
    x[X_IF_Q] = i_q
    ud = p[P_R] * i_d - w_e * lq * i_q
    uq = p[P_R] * i_q + w_e * (ld * i_d + psi)
    x[X_UD_APP] = ud
    x[X_UQ_APP] = uq
    x[X_INT_D] = ud - (-w_e * p[P_LQ_NOM] * i_q)
    x[X_INT_Q] = uq - w_e * (p[P_LD_NOM] * i_d + p[P_PSI_NOM])
    t_em = 1.5 * p[P_NP] * (psi * i_q + (ld - lq) * i_d * i_q)
    x[X_LOAD_INT] = -t_em + p[P_B] * w_m


class Plant:
    """Stateful convenience wrapper around `simulate` (used by tests, calibration and benchmarks)."""

    def __init__(self, params: np.ndarray, tab: np.ndarray | None = None, noise_seed: int | None = 0,
                 chunk: int = 256):
        self.p = np.asarray(params, dtype=np.float64).copy()
        self.tab = np.zeros(1) if tab is None else np.asarray(tab, dtype=np.float64)
        if tab is None:   # no tables: unsaturated machine, no disturbance map
            self.p[P_SAT_N] = self.p[P_DMAP_NT] = self.p[P_DMAP_NN] = 0.0
        self.x = new_state()
        self.rng = np.random.default_rng(noise_seed)
        self.chunk = chunk
        self.summary = np.zeros((1, N_SUMMARY))
        self._no_trace = np.zeros((0, N_TRACE))
        self._no_frames = np.zeros(0, dtype=np.uint8)
        self.samples = 0

    def init_op(self, torque_nm: float, speed_rpm: float, udc_v: float) -> None:
        steady_state_init(self.x, self.p, torque_nm, speed_rpm, udc_v, self.tab)

    def run(self, sp: np.ndarray, n: int, trace: bool = False, frames: bool = True):
        """Simulate n samples with setpoints sp (the chunk-rate task runs at samples 0, chunk, ...
        of this call). Returns (angle_counts, accel_counts, flags, trace)."""
        m = n
        noise = self.rng.standard_normal(m) if self.p[P_NOISE] > 0.0 else np.zeros(m)
        fr = np.empty(m * FRAME_BYTES, dtype=np.uint8) if frames else self._no_frames
        tr = np.zeros((m, N_TRACE)) if trace else self._no_trace
        self.summary = np.zeros((-(-m // self.chunk), N_SUMMARY))
        simulate(self.x, self.p, self.tab, np.asarray(sp, dtype=np.float64), noise, self.chunk, self.samples,
                 fr, self.summary, tr)
        self.samples += m
        if frames:
            f = np.frombuffer(fr.tobytes(), dtype=FRAME_DTYPE)
            angle, accel, flags = f["angle"].copy(), f["accel"].copy(), f["flags"].copy()
        else:
            angle = accel = flags = None
        return angle, accel, flags, (tr if trace else None)
