"""Physics of plant_emulator against closed-form answers (no CAN, no pty)."""

from __future__ import annotations

import math

import canopen
import numpy as np
import pytest
from scipy.linalg import expm

from drivers import DRIVE_EDS
from drivers.cia402 import State402
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta, whole_periods
from plant_emulator.drive_firmware import DriveFirmware

FS_HZ = 16000.0


@pytest.fixture(scope="module")
def bench():
    return scn.build(scn.load("paper-bench"))


@pytest.fixture(scope="module")
def params(bench) -> np.ndarray:
    return bench[0]


@pytest.fixture(scope="module")
def tab(bench) -> np.ndarray:
    return bench[1]


def quiet(p: np.ndarray) -> np.ndarray:
    """No disturbance, no sensor noise, no dead time: the fundamental-wave machine alone."""
    q = p.copy()
    q[ph.P_DIST_SCALE] = 0.0
    q[ph.P_NOISE] = 0.0
    q[ph.P_T_DEAD] = 0.0
    return q


def phasor(signal: np.ndarray, phi_e: np.ndarray, h: int) -> complex:
    n = len(signal)
    return complex(2.0 / n * np.sum(signal * np.cos(h * phi_e)), 2.0 / n * np.sum(signal * np.sin(h * phi_e)))


def test_zoh_matches_matrix_exponential(params):
    r, ld, lq, ts = 0.012, 18e-6, 25e-6, 1.0 / FS_HZ
    w_e = 900.0
    a = np.array([[-r / ld, w_e * lq / ld], [-w_e * ld / lq, -r / lq]])
    b = np.diag([1.0 / ld, 1.0 / lq])
    # augmented exponential gives Ad and Bd of the ZOH discretisation exactly
    m = np.zeros((4, 4))
    m[:2, :2], m[:2, 2:] = a * ts, b * ts
    e = expm(m)
    got = ph.zoh_dq(r, ld, lq, w_e, ts)
    np.testing.assert_allclose(np.reshape(got[:4], (2, 2)), e[:2, :2], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.reshape(got[4:], (2, 2)), e[:2, 2:], rtol=1e-9, atol=1e-15)


def test_steady_state_matches_dq_closed_form(params):
    """Base-speed OP from zero currents: i_d = 0, i_q = T/(1.5 N_p psi), u_d = -w_e L_q i_q,
    u_q = R i_q + w_e psi, T_em = T (eq. 18-20 at steady state), all within 1 %."""
    p = quiet(params)
    torque_nm, speed_rpm = 2.0, 1000.0
    w_m = speed_rpm * 2 * math.pi / 60
    w_e = p[ph.P_NP] * w_m
    plant = ph.Plant(p)
    plant.x[ph.X_OMEGA_M] = plant.x[ph.X_LOAD_REF] = w_m
    plant.x[ph.X_LOAD_INT] = -torque_nm  # load machine already holding the torque
    sp = op_setpoints(12.0, torque_nm, speed_rpm)
    plant.run(sp, int(0.3 * FS_HZ))
    tr = plant.run(sp, whole_periods(speed_rpm, p[ph.P_NP], FS_HZ, 20), trace=True)[3]
    r, l, psi, n_p = p[ph.P_R], p[ph.P_LQ], p[ph.P_PSI], p[ph.P_NP]
    iq = torque_nm / (1.5 * n_p * psi)
    ud, uq = -w_e * l * iq, r * iq + w_e * psi
    assert abs(tr[:, ph.TR_ID].mean()) < 0.01 * iq
    assert tr[:, ph.TR_IQ].mean() == pytest.approx(iq, rel=0.01)
    assert tr[:, ph.TR_UD].mean() == pytest.approx(ud, rel=0.01)
    assert tr[:, ph.TR_UQ].mean() == pytest.approx(uq, rel=0.01)
    assert tr[:, ph.TR_TORQUE].mean() == pytest.approx(torque_nm, rel=0.01)
    assert tr[:, ph.TR_OMEGA_M].mean() == pytest.approx(w_m, rel=0.01)


def test_injection_rotates_the_voltage_exactly(params):
    """|u*| = |u| for every sample (eq. 2-4), even for a large injection angle."""
    p = params.copy()
    plant = ph.Plant(p)
    ph.steady_state_init(plant.x, p, 2.5, 2000.0, 12.0)
    sp = op_setpoints(12.0, 2.5, 2000.0, theta_from_gamma_delta(math.radians(12.0), math.radians(40.0)))
    tr = plant.run(sp, 4000, trace=True)[3]
    u = np.hypot(tr[:, ph.TR_UD], tr[:, ph.TR_UQ])
    u_star = np.hypot(tr[:, ph.TR_UD_STAR], tr[:, ph.TR_UQ_STAR])
    assert np.max(np.abs(u_star / u - 1.0)) < 1e-9
    # and the angle moved by v_inj = theta^T x (eq. 3, 12)
    dphi = np.angle(
        np.exp(
            1j * (np.arctan2(tr[:, ph.TR_UQ_STAR], tr[:, ph.TR_UD_STAR]) - np.arctan2(tr[:, ph.TR_UQ], tr[:, ph.TR_UD]))
        )
    )
    np.testing.assert_allclose(dphi, tr[:, ph.TR_V_INJ], atol=1e-12)


def test_sync_flag_toggles_at_the_sample_the_setpoint_is_used(params):
    p = quiet(params)
    plant = ph.Plant(p)
    ph.steady_state_init(plant.x, p, 1.0, 1000.0, 12.0)
    sp = op_setpoints(12.0, 1.0, 1000.0)
    _, _, flags_a, tr_a = plant.run(sp, 256, trace=True)
    sp[ph.S_TORQUE_NM] = 2.0
    sp[ph.S_SYNC] = 1.0
    _, _, flags_b, tr_b = plant.run(sp, 256, trace=True)
    assert not np.any(flags_a & ph.SYNC_FLAG)
    assert np.all(flags_b & ph.SYNC_FLAG)
    # the controller output jumps at exactly that sample: K_p * delta i_q*
    d_iq = 1.0 / (1.5 * p[ph.P_NP] * p[ph.P_PSI_NOM])
    jump = tr_b[0, ph.TR_UQ] - tr_a[-1, ph.TR_UQ]
    assert jump == pytest.approx(p[ph.P_KP_Q] * d_iq, rel=0.02)
    assert abs(tr_a[-1, ph.TR_UQ] - tr_a[-2, ph.TR_UQ]) < 1e-6


def test_firmware_applies_one_setpoint_per_chunk_with_one_toggle(params):
    """Drive firmware: each accepted SDO write is one event, one toggle, at a chunk start."""
    net = canopen.Network()
    drive = DriveFirmware(net, 5, str(DRIVE_EDS))
    drive.state = State402.OPERATION_ENABLED
    node = drive.node
    od = node.object_dictionary
    node.set_data(0x6071, 0, od[0x6071].encode_raw(500), check_writable=True)
    node.set_data(0x2000, 3, od[0x2000][3].encode_raw(0.01), check_writable=True)
    node.set_data(0x2000, 4, od[0x2000][4].encode_raw(0.02), check_writable=True)
    node.set_data(0x2000, 2, od[0x2000][2].encode_raw(1), check_writable=True)
    node.set_data(0x2000, 7, od[0x2000][7].encode_raw(1), check_writable=True)
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.set_data(0x6071, 0, od[0x6071].encode_raw(1001), check_writable=True)
    assert exc.value.code == 0x06090030
    sp = ph.new_setpoints()
    levels = []
    for _ in range(3):  # torque, injection mode, theta commit
        assert drive.chunk_setpoints(sp, 12.0)
        levels.append(sp[ph.S_SYNC])
    assert levels == [1.0, 0.0, 1.0]
    assert not drive.chunk_setpoints(sp, 12.0) and sp[ph.S_SYNC] == 1.0
    assert sp[ph.S_TORQUE_NM] == pytest.approx(2.5)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((0.01, 0.02))
    assert sp[ph.S_POWER] == 1.0
    assert drive.chunk_setpoints(sp, 3.0) is False and sp[ph.S_POWER] == 0.0  # DC link too low


def test_calibrated_theta_cancels_the_6th_alpha_harmonic(params, tab):
    """paper-bench at OP1 {2.5 Nm, 2000 rpm, 12 V}: theta* from gamma = 3 deg, delta = 280 deg
    suppresses the 6th harmonic of the measured (noisy, quantised) acceleration by >= 40 dB."""
    p = params.copy()
    fs = p[ph.P_ALPHA_FS]
    n = whole_periods(2000.0, p[ph.P_NP], FS_HZ, 400)

    def alpha_harmonic(theta) -> float:
        plant = ph.Plant(p, tab, noise_seed=1)
        plant.init_op(2.5, 2000.0, 12.0)
        sp = op_setpoints(12.0, 2.5, 2000.0, theta)
        plant.run(sp, int(0.5 * FS_HZ))
        angle, accel, flags, _ = plant.run(sp, n)
        assert not np.any(flags & ph.OVER_RANGE_FLAG)
        # as the service sees it: DAQ counts back to rad and rad/s^2
        phi = angle.astype(float) * 2 * math.pi / 65536
        alpha = accel.astype(float) / 32767 * fs
        return abs(phasor(alpha, phi, 6))

    a_off = alpha_harmonic((0.0, 0.0))
    a_on = alpha_harmonic(theta_from_gamma_delta(math.radians(3.0), math.radians(280.0)))
    assert a_off > 0.02 * fs  # a clearly visible harmonic (a few % of full scale)
    assert 20 * math.log10(a_off / a_on) >= 40.0


def test_seed_perturbs_truth_within_ranges_not_firmware():
    base = scn.load("paper-bench")
    a, b = scn.load("paper-bench", seed=7), scn.load("paper-bench", seed=7)
    assert a.data == b.data
    for key in ("r_s_ohm", "l_d_h", "l_q_h", "psi_p_wb"):
        ratio = a.data["machine"][key] / base.data["machine"][key]
        assert 0.8 <= ratio <= 1.2
    assert a.data["firmware"] == base.data["firmware"]
    assert a.data["machine"] != base.data["machine"]


def test_a_disabled_bench_stays_at_standstill(params, tab):
    """Power stage and load machine off: no current, so no torque harmonic (it is the currents',
    flux and saturation harmonics times current). The speed-dependent phase of the map applied to a
    coasting shaft once drove it to a steady -6 rpm; now a shaft at rest stays at rest."""
    plant = ph.Plant(params, tab)
    sp = ph.new_setpoints(12.0)  # S_POWER = S_LOAD_ON = 0
    for _ in range(64):  # 1 s of plant time
        plant.run(sp, 256)
    assert abs(plant.x[ph.X_OMEGA_M]) < 1e-9
