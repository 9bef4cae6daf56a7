"""The control-period loop: one numba function that runs the stages in the order of the hardware.

One call of `simulate` advances drive firmware + inverter + PMSM + shaft + load machine + accelerometer
+ DAQ framing by n control periods T_s (1/16 kHz in paper-bench), in chunks of `chunk` samples
(setpoints are constant over a call; the chunk-rate firmware task runs at every chunk start). The
stages are small @njit(inline="always") functions in their own modules (firmware, inverter,
machine, mechanics, daq), each tested alone; here they are inlined into one loop over scalars so
the loop runs as fast as when it was written as one function.

Per control period k:
  1. firmware   current control on the measured (decoupled) currents (back-calculation anti-windup),
                field weakening, injection (rotation or eq. 11), torque estimate  (firmware.py)
  2. plant      disturbance d and T_em (machine.py), load machine, dw_m/dt, sensor H(z) (mechanics.py)
  3. DAQ        counts, flags and the frame of sample k                        (daq.py)
  4. inverter   dead-time error over the next period                           (inverter.py)
  5. advance    currents one ZOH period with u*(k-1) (the 1.5-period delay) plus dead time
                (machine.current_step), the decoupling estimate, |i| filter, shaft and angle.
The state lives in flat float64 arrays indexed by the X_*/P_*/S_* constants, each declared by the
stage that owns it (numba compiles them as constants); the scenario's tables (saturation,
disturbance map) live in one flat array `tab` whose offsets are in `p`. Units: SI (V, A, Ohm, H, Wb,
Nm, rad, rad/s, rad/s^2, kg m^2).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from drivers.daq_protocol import FRAME_DTYPE

from . import daq, firmware, inverter, machine, mechanics
from .daq import FRAME_BYTES, OVER_RANGE_FLAG, P_ALPHA_FS, S_SYNC, SYNC_FLAG
from .firmware import (
    MAX_INJECTION_ORDERS,
    P_FW_BW,
    P_FW_TARGET,
    P_IMAX,
    P_KI_D,
    P_KI_Q,
    P_KP_D,
    P_KP_Q,
    P_LD_NOM,
    P_LQ_NOM,
    P_PSI_NOM,
    P_R_NOM,
    P_TS,
    P_V_MARGIN,
    P_W_BW,
    S_DECOUPLING,
    S_H,
    S_POWER,
    S_THETA_COS,
    S_THETA_SIN,
    S_TORQUE_NM,
    S_UDC_V,
    S_VEST,
    S_XH_COS,
    S_XH_ORDER,
    S_XH_SIN,
    X_FW_DID,
    X_IF_D,
    X_IF_Q,
    X_IHAT_D,
    X_IHAT_Q,
    X_INT_D,
    X_INT_Q,
    X_VD_APP,
    X_VQ_APP,
)
from .inverter import P_ANGLE_COMP, P_F_PWM, P_I_ZC, P_T_DEAD, X_UD_APP, X_UQ_APP
from .machine import (
    MAX_FURTHER_HARMONICS,
    P_DMAP_NN,
    P_DMAP_NT,
    P_H_DIST,
    P_LD,
    P_LQ,
    P_NP,
    P_OFF_DECAY,
    P_PSI,
    P_R,
    P_SAT_DECAY,
    P_SAT_N,
    P_XH_N,
    X_ID,
    X_IMAG_F,
    X_IQ,
)
from .mechanics import (
    P_B,
    P_H_A1,
    P_H_A2,
    P_H_B0,
    P_H_B1,
    P_H_B2,
    P_J,
    P_LOAD_KI,
    P_LOAD_KP,
    P_LOAD_RAMP,
    P_LOAD_TMAX,
    P_NOISE,
    S_LOAD_ACCEL,
    S_LOAD_DECEL,
    S_LOAD_ON,
    S_LOAD_SPEED,
    X_H_S1,
    X_H_S2,
    X_LOAD_INT,
    X_LOAD_REF,
    X_OMEGA_M,
    X_PHI_E,
)

SQRT3 = math.sqrt(3.0)
TWO_PI = 2.0 * math.pi

N_PARAMS = 50  # p: indices declared by the stages (25, 26 unused)
N_SETPOINTS = 22  # sp
X_SAMPLES = 16  # samples simulated so far
N_STATE = 21  # x

# ---- per-chunk summary (rows of summary[n_chunks, N_SUMMARY]) ----
Y_UD_SUM = 0  # sum of nominal u_d over the chunk (V)
Y_UQ_SUM = 1
Y_TORQUE_EST_SUM = 2  # firmware torque estimate from measured currents, nominal params (Nm)
Y_OMEGA_SUM = 3
Y_LOAD_TORQUE_SUM = 4
Y_OVER_RANGE = 5  # count of clipped samples
Y_ID_REF = 6  # current references of the chunk (A)
Y_IQ_REF = 7
N_SUMMARY = 8

# ---- optional per-sample trace ----
TR_ID = 0
TR_IQ = 1
TR_UD = 2  # nominal control output u_dq (before injection)
TR_UQ = 3
TR_UD_STAR = 4  # after injection (what the inverter is told)
TR_UQ_STAR = 5
TR_TORQUE = 6  # T_em including d
TR_DIST = 7  # d
TR_ALPHA = 8  # true dw_m/dt
TR_ALPHA_MEAS = 9  # sensor output before quantisation
TR_PHI_E = 10
TR_OMEGA_M = 11
TR_V_INJ = 12
TR_T_LOAD = 13  # load machine torque T_lm
TR_UD_DT = 14  # dead-time voltage error in dq (applied with u*)
TR_UQ_DT = 15
N_TRACE = 16

OMEGA_RECOMPUTE_RAD_S = 0.05  # electrical rad/s change that triggers a new matrix exponential


@njit(cache=True, inline="always")
def _store_chunk_sums(summary, row, s_ud, s_uq, s_te, s_w, s_tl, n_over):
    """The per-chunk sums of one finished chunk into its summary row."""
    summary[row, Y_UD_SUM] = s_ud
    summary[row, Y_UQ_SUM] = s_uq
    summary[row, Y_TORQUE_EST_SUM] = s_te
    summary[row, Y_OMEGA_SUM] = s_w
    summary[row, Y_LOAD_TORQUE_SUM] = s_tl
    summary[row, Y_OVER_RANGE] = n_over


@njit(cache=True, nogil=True)
def simulate(x, p, tab, sp, theta_schedule, noise, chunk, seq0, frames, summary, trace):
    """Advance the bench by n = len(noise) control periods in place.

    x: state (N_STATE), p: parameters (N_PARAMS), tab: tables, sp: setpoints (N_SETPOINTS), theta_schedule:
    LUT mode's theta against shaft speed (rows w_m rad/s, theta_cos, theta_sin; firmware.scheduled_theta),
    taken at every chunk-rate task, or shape (0, 3): the setpoints' theta for the whole call. noise: n
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
    # further injection orders (firmware S_XH_*): their own theta, constant over the call
    n_xi = 0
    xi_order = np.zeros(MAX_INJECTION_ORDERS - 1, dtype=np.int64)
    xi_c = np.zeros(MAX_INJECTION_ORDERS - 1)
    xi_s = np.zeros(MAX_INJECTION_ORDERS - 1)
    for kk in range(MAX_INJECTION_ORDERS - 1):
        order_k = int(sp[S_XH_ORDER + kk] + 0.5)
        if order_k > 0 and (sp[S_XH_COS + kk] != 0.0 or sp[S_XH_SIN + kk] != 0.0):
            xi_order[n_xi] = order_k
            xi_c[n_xi] = sp[S_XH_COS + kk]
            xi_s[n_xi] = sp[S_XH_SIN + kk]
            n_xi += 1
    inject = th_c != 0.0 or th_s != 0.0 or n_xi > 0
    scheduled = theta_schedule.shape[0] > 0
    h_int = int(sp[S_H] + 0.5)
    decouple = sp[S_DECOUPLING] > 0.5
    vest = sp[S_VEST] > 0.5
    udc = sp[S_UDC_V]
    u_lim = udc / SQRT3
    load_on = sp[S_LOAD_ON] > 0.5
    load_target = sp[S_LOAD_SPEED]
    sync_bits = SYNC_FLAG if sp[S_SYNC] > 0.5 else 0
    h_dist_int = int(p[P_H_DIST] + 0.5)
    same_h = h_dist_int == h_int
    # further torque harmonics of their own (machine.map_phasor k >= 1): orders, phasors per chunk
    n_xh = int(p[P_XH_N]) if p[P_DMAP_NT] > 0.0 and p[P_DMAP_NN] > 0.0 else 0  # no map: no tables to read
    xh_order = np.zeros(MAX_FURTHER_HARMONICS, dtype=np.int64)
    xh_x = np.zeros(MAX_FURTHER_HARMONICS)
    xh_y = np.zeros(MAX_FURTHER_HARMONICS)
    xh_mult = np.zeros(MAX_FURTHER_HARMONICS, dtype=np.int64)  # order / h where a multiple of it, else 0
    for kk in range(n_xh):
        xh_order[kk] = machine.further_order(p, tab, kk + 1)
        if h_dist_int > 0 and xh_order[kk] % h_dist_int == 0:
            xh_mult[kk] = xh_order[kk] // h_dist_int
    xh_on = False
    b0 = p[P_H_B0]
    b1 = p[P_H_B1]
    b2 = p[P_H_B2]
    a1 = p[P_H_A1]
    a2 = p[P_H_A2]
    fs = p[P_ALPHA_FS]
    sigma = p[P_NOISE]
    # the load's ramps per period: its setpoints (0x6083 / 0x6084), else the scenario's
    ramp_up = (sp[S_LOAD_ACCEL] if sp[S_LOAD_ACCEL] > 0.0 else p[P_LOAD_RAMP]) * ts
    ramp_down = (sp[S_LOAD_DECEL] if sp[S_LOAD_DECEL] > 0.0 else p[P_LOAD_RAMP]) * ts
    tmax = p[P_LOAD_TMAX]
    load_kp = p[P_LOAD_KP]
    load_ki = p[P_LOAD_KI]
    j_shaft = p[P_J]
    b_fric = p[P_B]
    off_decay = p[P_OFF_DECAY]
    # dead time: amplitude of the per-phase voltage error, smoothing of sgn(i)
    dt_amp = udc * p[P_T_DEAD] * p[P_F_PWM]
    dead_time = dt_amp > 0.0 and power
    izc = p[P_I_ZC] if p[P_I_ZC] > 0.0 else 1e-12
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
    zoh_true = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # machine, true parameters
    zoh_nom = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # the firmware's nominal model (decoupling)
    app_c = 1.0  # inverter: dq average of the applied voltage = u* (app_c + j app_s)
    app_s = 0.0
    rot_c = 1.0  # rotation by half a period (dead-time error at the middle of the period)
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
                id_ff, iq_ff = firmware.current_reference(
                    torque_ref, w_e, udc, r_nom, ld_nom, lq_nom, psi_nom, n_p, p[P_IMAX], p[P_V_MARGIN]
                )
            else:
                id_ff = 0.0
                iq_ff = 0.0
                fw_did = 0.0
            id_ref = id_ff + fw_did
            iq_ref = iq_ff
            if scheduled:
                th_c, th_s = firmware.scheduled_theta(theta_schedule, w_m)
                inject = th_c != 0.0 or th_s != 0.0 or n_xi > 0
            aw_l = abs(w_e) * ld_nom
            fw_gain = p[P_FW_BW] * ts / aw_l if (aw_l > 0.0 and power) else 0.0
            fw_did_min = -p[P_IMAX] - id_ff
            ld, lq, psi = machine.saturated_params(p, tab, imag_f)
            # the harmonic is the currents' (flux and saturation harmonics times current): none while the
            # power stage is off. Its phase map depends on speed, so applied to a coasting shaft it would
            # drive it (a disabled bench crept at -6 rpm)
            d_x, d_y = machine.disturbance_phasor(p, tab, torque_ref, w_m) if power else (0.0, 0.0)
            d_on = d_x != 0.0 or d_y != 0.0
            xh_on = False
            for kk in range(n_xh):
                xh_x[kk], xh_y[kk] = machine.map_phasor(p, tab, kk + 1, torque_ref, w_m) if power else (0.0, 0.0)
                xh_on = xh_on or xh_x[kk] != 0.0 or xh_y[kk] != 0.0
            zoh_true = machine.zoh_dq(r, ld, lq, w_e, ts)
            zoh_nom = machine.zoh_dq(r_nom, ld_nom, lq_nom, w_e, ts)
            w_zoh = w_e
            app_c, app_s, rot_c, rot_s = inverter.zoh_average(w_e, ts, angle_comp)
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
        chp, shp = machine.harmonic(cphi, sphi, h_int)

        # ---------------- 1. firmware: current control at sample k ----------------
        if power:
            id_fb = i_d
            iq_fb = i_q
            if decouple:
                # section 3.1: the estimated injection-caused currents are not fed back
                id_fb -= ihat_d
                iq_fb -= ihat_q
            u_d, u_q, mag, int_d, int_q = firmware.pi_current(
                id_ref, iq_ref, id_fb, iq_fb, int_d, int_q, w_e, kp_d, kp_q, ki_d, ki_q, ld_nom, lq_nom, psi_nom, u_lim
            )
            if fw_gain > 0.0:
                fw_did, id_ref, iq_ref = firmware.field_weakening(
                    fw_did, mag, fw_gain, u_fw_target, fw_did_min, id_ff, iq_ff, i_max2
                )
            if vest:
                uh_d, uh_q, if_d, if_q = firmware.voltage_estimate(
                    id_ref, iq_ref, if_d, if_q, w_e, w_bw, g_cl, r_nom, ld_nom, lq_nom, psi_nom, u_lim
                )
            else:
                uh_d = u_d
                uh_q = u_q
                if_d = id_ref
                if_q = iq_ref
            if inject:
                v_inj = firmware.injection_angle(th_c, th_s, chp, shp)
                for kk in range(n_xi):  # every further order adds its angle: one rotation by the sum
                    if h_int > 0 and xi_order[kk] % h_int == 0:
                        ck, sk = machine.harmonic(chp, shp, xi_order[kk] // h_int)
                    else:
                        ck, sk = machine.harmonic(cphi, sphi, xi_order[kk])
                    v_inj += firmware.injection_angle(xi_c[kk], xi_s[kk], ck, sk)
                u_ds, u_qs = firmware.inject(u_d, u_q, uh_d, uh_q, v_inj, vest, u_lim)
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
        te_est = firmware.torque_estimate(i_d, i_q, k_t_nom, n_p, ld_nom, lq_nom)

        # ---------------- 2. plant: torque, shaft, sensor at sample k ----------------
        dist = 0.0
        if d_on or xh_on:
            if same_h:
                cx = chp
                sx = shp
            else:
                cx, sx = machine.harmonic(cphi, sphi, h_dist_int)
            dist = machine.harmonic_torque(d_x, d_y, cx, sx)
            for kk in range(n_xh):
                # a multiple of the map's order from its cos/sin: one squaring for the 12th, not four
                if xh_mult[kk] > 0:
                    ck, sk = machine.harmonic(cx, sx, xh_mult[kk])
                else:
                    ck, sk = machine.harmonic(cphi, sphi, xh_order[kk])
                dist += machine.harmonic_torque(xh_x[kk], xh_y[kk], ck, sk)
        t_em = machine.torque(i_d, i_q, psi, ld, lq, n_p) + dist
        t_lm, load_ref, load_int = mechanics.load_machine(
            load_on, load_ref, load_int, load_target, w_m, ramp_up, ramp_down, load_kp, load_ki, j_shaft, ts, tmax
        )
        alpha = mechanics.shaft_acceleration(t_em, t_lm, b_fric, w_m, j_shaft)
        y, hs1, hs2 = mechanics.sensor_step(alpha, b0, b1, b2, a1, a2, hs1, hs2)
        a_meas = y + sigma * noise[k]

        # ---------------- 3. DAQ: counts, flags, frame of sample k ----------------
        raw, over = daq.accel_counts(a_meas, fs)
        fl = sync_bits
        if over:
            fl |= OVER_RANGE_FLAG
            n_over += 1
        if write_frames:
            daq.write_frame(frames, k * FRAME_BYTES, seq, phi, raw, fl)
            seq += 1

        # ---------------- 4. inverter: dead-time error over the next period ----------------
        ed = 0.0
        eq = 0.0
        if dead_time:
            # exact period mean along the currents' own path: their value at the end of the period is
            # predicted with the voltage held over it plus the error (which itself flattens a phase
            # current near zero), a few fixed-point passes from the error without it. A sgn band of
            # 0.5 |i| w_e T_s assumed the fundamental's slope (at 2 Nm / 800 rpm ~10 % off at the
            # crossings): the harmonic then depended on where the crossings fell on the sample grid, a
            # phase that 800 rpm (exactly 300 samples per electrical turn) kept for a whole run.
            ue_d, ue_q = inverter.applied_voltage(ud_app, uq_app, app_c, app_s, 0.0, 0.0)
            i1_d, i1_q = machine.current_step(zoh_true, i_d, i_q, ue_d, ue_q - w_e * psi)
            ed, eq = inverter.dead_time_voltage(i_d, i_q, i1_d, i1_q, cphi, sphi, rot_c, rot_s, dt_amp, izc)
            for _ in range(3):
                i1_d, i1_q = machine.current_step(zoh_true, i_d, i_q, ue_d + ed, ue_q + eq - w_e * psi)
                ed, eq = inverter.dead_time_voltage(i_d, i_q, i1_d, i1_q, cphi, sphi, rot_c, rot_s, dt_amp, izc)

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

        # ---------------- 5. advance to k+1 ----------------
        if power:
            if abs(w_e - w_zoh) > OMEGA_RECOMPUTE_RAD_S:
                # the exponential depends on w_e only; a 0.05 rad/s step changes the cross-coupling
                # voltage by ~1e-4 V at I_max, so recomputing on change is as good as every period
                zoh_true = machine.zoh_dq(r, ld, lq, w_e, ts)
                if decouple:
                    zoh_nom = machine.zoh_dq(r_nom, ld_nom, lq_nom, w_e, ts)
                w_zoh = w_e
            # u*(k-1) held over this period (1.5-period delay) plus dead time; back-EMF of eq. 19
            ue_d, ue_q = inverter.applied_voltage(ud_app, uq_app, app_c, app_s, ed, eq)
            i_d, i_q = machine.current_step(zoh_true, i_d, i_q, ue_d, ue_q - w_e * psi)
            if decouple:
                # nominal model of the currents the applied injection voltage causes (section 3.1)
                ihat_d, ihat_q = machine.current_step(zoh_nom, ihat_d, ihat_q, vd_app, vq_app)
            else:
                ihat_d = 0.0
                ihat_q = 0.0
            ud_app = u_ds
            uq_app = u_qs
            vd_app = u_ds - u_d
            vq_app = u_qs - u_q
        else:
            # inverter off: the currents commutate into the DC link through the diodes and die out
            i_d *= off_decay
            i_q *= off_decay
            ud_app = 0.0
            uq_app = 0.0
            vd_app = 0.0
            vq_app = 0.0
            ihat_d = 0.0
            ihat_q = 0.0
        imag_f = sat_decay * imag_f + (1.0 - sat_decay) * math.sqrt(i_d * i_d + i_q * i_q)
        w_m, phi = mechanics.shaft_advance(w_m, phi, alpha, n_p, ts)

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

NO_THETA_SCHEDULE = np.zeros((0, 3))  # simulate: the setpoints' theta for the whole call


def new_state() -> np.ndarray:
    return np.zeros(N_STATE)


def new_setpoints(udc_v: float = 0.0) -> np.ndarray:
    sp = np.zeros(N_SETPOINTS)
    sp[S_H] = 6.0
    sp[S_UDC_V] = udc_v
    return sp


def steady_state_init(
    x: np.ndarray, p: np.ndarray, torque_nm: float, speed_rpm: float, udc_v: float, tab: np.ndarray | None = None
) -> None:
    """Put the state near the steady state of an operating point (no injection, no d, no dead time):
    the firmware's current references, integrators at what the true machine needs beyond the
    feed-forward, shaft at speed with the load machine holding it. Saves settling time in tests and
    calibration (the remaining transient, e.g. the dead-time voltage, settles within ~10 ms)."""
    w_m = speed_rpm * TWO_PI / 60.0
    w_e = p[P_NP] * w_m
    i_d, i_q = firmware.current_reference(
        torque_nm, w_e, udc_v, p[P_R_NOM], p[P_LD_NOM], p[P_LQ_NOM], p[P_PSI_NOM], p[P_NP], p[P_IMAX], p[P_V_MARGIN]
    )
    ld, lq, psi = p[P_LD], p[P_LQ], p[P_PSI]
    if tab is not None:
        ld, lq, psi = machine.saturated_params(p, tab, math.hypot(i_d, i_q))
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
    t_em = machine.torque(i_d, i_q, psi, ld, lq, p[P_NP])
    x[X_LOAD_INT] = -t_em + p[P_B] * w_m


class Plant:
    """Stateful convenience wrapper around `simulate` (used by tests, calibration and benchmarks)."""

    def __init__(self, params: np.ndarray, tab: np.ndarray | None = None, noise_seed: int | None = 0, chunk: int = 256):
        self.p = np.asarray(params, dtype=np.float64).copy()
        self.tab = np.zeros(1) if tab is None else np.asarray(tab, dtype=np.float64)
        if tab is None:  # no tables: unsaturated machine, no disturbance map
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

    def run(self, sp: np.ndarray, n: int, trace: bool = False, frames: bool = True, theta_schedule=None):
        """Simulate n samples with setpoints sp (the chunk-rate task runs at samples 0, chunk, ...
        of this call; theta_schedule: see `simulate`). Returns (angle_counts, accel_counts, flags, trace)."""
        m = n
        noise = self.rng.standard_normal(m) if self.p[P_NOISE] > 0.0 else np.zeros(m)
        fr = np.empty(m * FRAME_BYTES, dtype=np.uint8) if frames else self._no_frames
        tr = np.zeros((m, N_TRACE)) if trace else self._no_trace
        self.summary = np.zeros((-(-m // self.chunk), N_SUMMARY))
        simulate(
            self.x,
            self.p,
            self.tab,
            np.asarray(sp, dtype=np.float64),
            NO_THETA_SCHEDULE if theta_schedule is None else np.asarray(theta_schedule, dtype=np.float64),
            noise,
            self.chunk,
            self.samples,
            fr,
            self.summary,
            tr,
        )
        self.samples += m
        # None: no frames asked for
        angle: np.ndarray | None
        accel: np.ndarray | None
        flags: np.ndarray | None
        if frames:
            f = np.frombuffer(fr.tobytes(), dtype=FRAME_DTYPE)
            angle, accel, flags = f["angle"].copy(), f["accel"].copy(), f["flags"].copy()
        else:
            angle = accel = flags = None
        return angle, accel, flags, (tr if trace else None)
