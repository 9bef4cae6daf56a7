"""Each stage of plant_emulator.physics alone, against a closed form or an independent computation.

The stages are the @njit functions the control-period loop inlines (plant_emulator/physics/loop.py);
here they are called one at a time from Python with hand-picked inputs. Units as in the stages: V, A,
Ohm, H, Wb, Nm, rad, rad/s, s.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.signal import lfilter

from drivers.daq_protocol import FrameDecoder, encode_frames
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta
from plant_emulator.physics import daq, firmware, inverter, loop, machine, mechanics

TS = 1.0 / 16000.0
R, LD, LQ, PSI, NP = 0.012, 18e-6, 25e-6, 0.004, 4


# ---------------------------------------------------------------------------------------------
# index layout: every stage declares its own indices; together they must not collide


def _indices(prefix: str) -> dict[str, int]:
    """Every index a stage declares, a block (a module's INDEX_BLOCKS: name -> width) as one name per index."""
    found: dict[str, int] = {}
    for module in (firmware, inverter, machine, mechanics, daq, loop):
        blocks = getattr(module, "INDEX_BLOCKS", {})
        for name, value in vars(module).items():
            if name.startswith(prefix) and isinstance(value, int) and name.isupper():
                for k in range(blocks.get(name, 1)):
                    key = f"{name}+{k}" if k else name
                    assert found.get(key, value + k) == value + k, f"{name} declared twice with different values"
                    found[key] = value + k
    return found


@pytest.mark.parametrize(
    "prefix, size",
    [("P_", ph.N_PARAMS), ("S_", ph.N_SETPOINTS), ("X_", ph.N_STATE), ("Y_", ph.N_SUMMARY), ("TR_", ph.N_TRACE)],
)
def test_the_stages_index_constants_are_distinct_and_fit_their_array(prefix, size):
    found = _indices(prefix)
    assert len(set(found.values())) == len(found), "two names share one index"
    assert all(0 <= i < size for i in found.values())
    if prefix != "P_":  # p leaves 25 and 26 unused
        assert sorted(found.values()) == list(range(size))
    assert all(getattr(ph, name) == i for name, i in found.items() if "+" not in name)  # the package exports them all


# ---------------------------------------------------------------------------------------------
# machine


@pytest.mark.parametrize("w_e", [0.0, 900.0, -3000.0])
def test_dq_current_step_equals_the_matrix_exponential_solution(w_e):
    """i(T_s) of L di/dt = u - R i + rotation terms with u constant over the period: the augmented
    matrix exponential expm([[A, B], [0, 0]] T_s) (w_e = 0 makes the eigenvalues real)."""
    a = np.array([[-R / LD, w_e * LQ / LD], [-w_e * LD / LQ, -R / LQ]])
    b = np.diag([1.0 / LD, 1.0 / LQ])
    m = np.zeros((4, 4))
    m[:2, :2], m[:2, 2:] = a * TS, b * TS
    e = expm(m)
    i0, u = np.array([3.0, -40.0]), np.array([0.7, -1.9])
    want = e[:2, :2] @ i0 + e[:2, 2:] @ u
    got = machine.current_step(machine.zoh_dq(R, LD, LQ, w_e, TS), i0[0], i0[1], u[0], u[1])
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11)


def test_torque_is_eq_20_and_a_harmonic_its_phasor():
    i_d, i_q = -12.0, 55.0
    assert machine.torque(i_d, i_q, PSI, LD, LQ, NP) == pytest.approx(
        1.5 * NP * (PSI * i_q + (LD - LQ) * i_d * i_q), rel=1e-15
    )
    big_d, phi_d = 0.05, 1.1
    for h in (6, 12, 18):
        for phi in np.linspace(0.0, 2 * math.pi, 13):
            cx, sx = machine.harmonic(math.cos(phi), math.sin(phi), h)
            assert (cx, sx) == pytest.approx((math.cos(h * phi), math.sin(h * phi)), abs=1e-13)
            got = machine.harmonic_torque(big_d * math.cos(phi_d), big_d * math.sin(phi_d), cx, sx)
            assert got == pytest.approx(big_d * math.cos(h * phi + phi_d), abs=1e-14)


# ---------------------------------------------------------------------------------------------
# inverter


@pytest.mark.parametrize("angle_comp", [True, False])
def test_zoh_average_is_the_mean_dq_voltage_of_the_held_vector(angle_comp):
    """The firmware computes u* at sample k; the inverter holds u* e^{j(phi_k + c)} (c = 1.5 w_e T_s with
    angle compensation, else 0) in alpha-beta during [T_s, 2 T_s] while the rotor turns on: the dq mean
    is (1/T_s) integral of u* e^{j(c - w_e t)} dt over that period, taken here on a fine grid."""
    w_e = 2 * math.pi * 133.3 * NP
    c = 1.5 * w_e * TS if angle_comp else 0.0
    t = np.linspace(TS, 2 * TS, 200001)
    mean = np.trapezoid(np.exp(1j * (c - w_e * t)), t) / TS
    app_c, app_s, rot_c, rot_s = inverter.zoh_average(w_e, TS, angle_comp)
    assert complex(app_c, app_s) == pytest.approx(mean, abs=1e-10)
    assert complex(rot_c, rot_s) == pytest.approx(cmath.exp(0.5j * w_e * TS), abs=1e-15)
    vd, vq = inverter.applied_voltage(2.0, 5.0, app_c, app_s, 0.1, -0.2)
    assert complex(vd, vq) == pytest.approx((2 + 5j) * complex(app_c, app_s) + (0.1 - 0.2j), abs=1e-14)


def _dead_time_by_phases(i0_dq, i1_dq, phi0, w_e, dt_amp, i_zc, steps=200_001):
    """Independent: the phase currents at the start (angle phi0) and the end (phi0 + w_e T_s) of the
    period by the inverse Park/Clarke, each phase linear in between, -dt_amp clip(i_x / i_zc, -1, 1)
    averaged over the period numerically (midpoint rule), back by the amplitude-invariant Clarke and
    Park transforms at the middle of the period."""
    angles = np.array([0.0, -2 * math.pi / 3, 2 * math.pi / 3])

    def phases(i_dq, phi):
        return i_dq[0] * np.cos(phi + angles) - i_dq[1] * np.sin(phi + angles)

    start, end = phases(i0_dq, phi0), phases(i1_dq, phi0 + w_e * TS)
    f = (np.arange(steps) + 0.5) / steps
    paths = start[:, None] + (end - start)[:, None] * f[None, :]
    e_ph = -dt_amp * np.mean(np.clip(paths / i_zc, -1.0, 1.0), axis=1)
    e_ab = (2.0 / 3.0) * np.sum(e_ph * np.exp(-1j * angles))  # Clarke: phase b at +120 deg
    e_dq = e_ab * cmath.exp(-1j * (phi0 + 0.5 * w_e * TS))
    return e_dq.real, e_dq.imag


@pytest.mark.parametrize(
    "i0, i1, w_e",
    [((-5.0, 60.0), (-5.2, 60.3), 800.0), ((0.0, 0.3), (0.05, 0.2), 800.0), ((-2.0, 1.0), (-1.9, 1.1), 20.0)],
)
def test_dead_time_voltage_is_the_per_phase_mean_along_the_currents_path(i0, i1, w_e):
    """Per phase the period mean of -U_dc T_dead f_pwm sgn(i_x), sgn linear within +-i_zc, for a phase
    current going linearly from its start to its end value (crossings anywhere in the period, at any
    slope), at the middle of the period in dq."""
    udc, t_dead, f_pwm, i_zc = 12.0, 1e-6, 16000.0, 0.5
    dt_amp = udc * t_dead * f_pwm
    half = 0.5 * w_e * TS
    for phi in np.linspace(0.0, 2 * math.pi, 37):
        got = inverter.dead_time_voltage(
            *i0, *i1, math.cos(phi), math.sin(phi), math.cos(half), math.sin(half), dt_amp, i_zc
        )
        want = _dead_time_by_phases(i0, i1, phi, w_e, dt_amp, i_zc)
        np.testing.assert_allclose(got, want, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# mechanics


PAPER_ZERO, PAPER_POLE = -35954.0, complex(-19.6, 6746.2)  # G_Salpha, section 2.3, rad/s


def _analog_h(s: complex) -> complex:
    """H(s) = J G_Salpha(s) normalised to H(0) = 1: |p|^2/(-z) (s - z) / ((s - p)(s - p*))."""
    w0_sq = abs(PAPER_POLE) ** 2
    return w0_sq / (-PAPER_ZERO) * (s - PAPER_ZERO) / ((s - PAPER_POLE) * (s - PAPER_POLE.conjugate()))


def _sensor_params():
    p = np.zeros(ph.N_PARAMS)
    p[ph.P_TS] = TS
    p[[ph.P_H_B0, ph.P_H_B1, ph.P_H_B2, ph.P_H_A1, ph.P_H_A2]] = mechanics.sensor_biquad(
        PAPER_ZERO, PAPER_POLE.real, PAPER_POLE.imag, TS
    )
    return p


def test_sensor_biquad_frequency_response_is_h_of_s_at_the_prewarped_frequency():
    """Bilinear with pre-warping at w0 = |p|: H(e^{j w T_s}) = H_a(j w_a), w_a = w0 tan(w T_s/2) /
    tan(w0 T_s/2), exactly; so H(1) = 1 and the resonance sits at w0 itself."""
    p = _sensor_params()
    w0 = abs(PAPER_POLE)
    assert mechanics.sensor_response(p, 0.0) == pytest.approx(1.0, abs=1e-12)
    for w in (2 * math.pi * 800, 2 * math.pi * 1000, w0, 2 * math.pi * 3000, 0.9 * math.pi / TS):
        w_a = w0 * math.tan(w * TS / 2) / math.tan(w0 * TS / 2)
        want = _analog_h(1j * w_a)
        assert mechanics.sensor_response(p, w) == pytest.approx(want, rel=1e-9)


def test_sensor_step_runs_the_biquad_difference_equation():
    """The DF2T recursion against scipy's lfilter of the same coefficients (an impulse and a ramp)."""
    p = _sensor_params()
    b = [p[ph.P_H_B0], p[ph.P_H_B1], p[ph.P_H_B2]]
    a = [1.0, p[ph.P_H_A1], p[ph.P_H_A2]]
    u = np.zeros(600)
    u[0] = 1.0
    u[100:] += 0.01 * np.arange(500)
    s1 = s2 = 0.0
    got = []
    for value in u:
        y, s1, s2 = mechanics.sensor_step(value, *b, *a[1:], s1, s2)
        got.append(y)
    np.testing.assert_allclose(got, lfilter(b, a, u), rtol=1e-12, atol=1e-12)


def test_load_machine_ramps_clamps_and_switches_on_bumplessly():
    kp, ki, j, tmax, ramp = 0.05, 2.0, 1e-3, 3.0, 0.5
    # ramping up: reference one ramp step on, T = K_p e + integral + J ramp / T_s
    t, ref, integ = mechanics.load_machine(True, 100.0, 0.2, 200.0, 99.0, ramp, ramp, kp, ki, j, TS, tmax * 100)
    assert ref == 100.5 and t == pytest.approx(kp * 1.5 + 0.2 + j * ramp / TS)
    assert integ == pytest.approx(0.2 + ki * TS * 1.5)
    # near the target the reference lands on it; a saturated torque stops the integrator
    t, ref, integ = mechanics.load_machine(True, 199.8, 0.2, 200.0, 150.0, ramp, ramp, kp, ki, j, TS, tmax)
    assert ref == 200.0 and t == tmax and integ == 0.2
    # off: no torque, the reference follows the shaft
    assert mechanics.load_machine(False, 5.0, 1.0, 200.0, 150.0, ramp, ramp, kp, ki, j, TS, tmax) == (0.0, 150.0, 0.0)


@pytest.mark.parametrize(
    ("ref", "target", "step"),
    [
        (100.0, 200.0, 0.5),
        (100.0, 0.0, -2.0),
        (-100.0, -200.0, -0.5),
        (-100.0, 0.0, 2.0),
        (0.0, 50.0, 0.5),
        (1.0, -50.0, -2.0),
    ],
    ids=["up", "down", "up-reverse", "down-reverse", "from-standstill", "through-standstill"],
)
def test_load_machine_accelerates_away_from_standstill_and_decelerates_towards_it(ref, target, step):
    """ramp_up (CiA 402 profile acceleration) while |speed| grows, ramp_down (deceleration) while it falls."""
    _, new_ref, _ = mechanics.load_machine(True, ref, 0.0, target, ref, 0.5, 2.0, 0.05, 2.0, 1e-3, TS, 1e9)
    assert new_ref == pytest.approx(ref + step)


def test_shaft_acceleration_and_trapezoidal_angle():
    assert mechanics.shaft_acceleration(2.0, -1.5, 1e-4, 200.0, 2e-4) == pytest.approx((0.5 - 0.02) / 2e-4)
    w, phi = mechanics.shaft_advance(200.0, 6.28, 1000.0, NP, TS)
    assert w == pytest.approx(200.0 + TS * 1000.0)
    assert phi == pytest.approx((6.28 + NP * TS * 0.5 * (200.0 + w)) - 2 * math.pi)  # wrapped


# ---------------------------------------------------------------------------------------------
# firmware


def test_pi_current_inside_the_limit_integrates_and_outside_scales_and_tracks_back():
    args = dict(kp_d=0.2, kp_q=0.3, ki_d=0.01, ki_q=0.02, ld_nom=LD, lq_nom=LQ, psi_nom=PSI)
    w_e = 800.0
    u_d, u_q, mag, int_d, int_q = firmware.pi_current(1.0, 50.0, 0.5, 49.0, 0.1, -0.2, w_e, u_lim=100.0, **args)
    assert u_d == pytest.approx(0.2 * 0.5 + 0.1 - w_e * LQ * 50.0)
    assert u_q == pytest.approx(0.3 * 1.0 - 0.2 + w_e * (LD * 1.0 + PSI))
    assert mag == pytest.approx(math.hypot(u_d, u_q))
    assert (int_d, int_q) == pytest.approx((0.1 + 0.01 * 0.5, -0.2 + 0.02 * 1.0))
    u_d2, u_q2, mag2, int_d2, int_q2 = firmware.pi_current(
        1.0, 50.0, 0.5, 49.0, 0.1, -0.2, w_e, u_lim=0.5 * mag, **args
    )
    assert mag2 == mag and math.hypot(u_d2, u_q2) == pytest.approx(0.5 * mag)
    assert math.atan2(u_q2, u_d2) == pytest.approx(math.atan2(u_q, u_d))
    # back-calculation: integrate, then track back by the cut-off part at K_i T_s / K_p per axis
    assert int_d2 == pytest.approx(0.1 + 0.01 * 0.5 - 0.01 / 0.2 * (u_d - u_d2))
    assert int_q2 == pytest.approx(-0.2 + 0.02 * 1.0 - 0.02 / 0.3 * (u_q - u_q2))


def test_pi_current_in_lasting_saturation_forgets_where_its_integrators_started():
    # a plant the limit cannot satisfy (error held): any start converges to one integrator state
    args = dict(kp_d=0.02, kp_q=0.02, ki_d=6e-4, ki_q=6e-4, ld_nom=LD, lq_nom=LQ, psi_nom=PSI)
    ends = []
    for int0 in ((0.0, 0.0), (-1.4, 1.1), (2.0, -3.0)):
        int_d, int_q = int0
        for _ in range(20000):
            u_d, u_q, mag, int_d, int_q = firmware.pi_current(
                -113.0, 0.0, -108.0, -60.0, int_d, int_q, 1340.0, u_lim=6.93, **args
            )
        assert mag > 6.93
        ends.append((int_d, int_q))
    for e in ends[1:]:
        assert e == pytest.approx(ends[0], abs=1e-9)


def test_injection_rotates_exactly_and_the_eq_11_variant_rotates_the_estimate():
    u_d, u_q, v = -1.2, 6.5, 0.07
    th_c, th_s, c6, s6 = 0.03, -0.04, math.cos(1.3), math.sin(1.3)
    assert firmware.injection_angle(th_c, th_s, c6, s6) == pytest.approx(th_c * c6 + th_s * s6)
    u_ds, u_qs = firmware.inject(u_d, u_q, 0.0, 0.0, v, False, 100.0)
    assert complex(u_ds, u_qs) == pytest.approx(complex(u_d, u_q) * cmath.exp(1j * v), abs=1e-14)
    uh_d, uh_q = -1.0, 6.0
    u_ds, u_qs = firmware.inject(u_d, u_q, uh_d, uh_q, v, True, 100.0)
    want = complex(u_d, u_q) + (cmath.exp(1j * v) - 1) * complex(uh_d, uh_q)
    assert complex(u_ds, u_qs) == pytest.approx(want, abs=1e-14)
    u_ds, u_qs = firmware.inject(u_d, u_q, uh_d, uh_q, v, True, 5.0)  # limited to |u*| = 5 V
    assert abs(complex(u_ds, u_qs)) == pytest.approx(5.0) and cmath.phase(complex(u_ds, u_qs)) == pytest.approx(
        cmath.phase(want)
    )


def test_voltage_estimate_in_steady_state_is_the_nominal_machine_voltage():
    """Eq. 11 with i* through G_cl settled (if = i*): u_hat0 = [R i_d - w L_q i_q, R i_q + w (L_d i_d + psi)]."""
    w_e, i_d, i_q = 900.0, -3.0, 40.0
    w_bw = 2 * math.pi * 1000
    uh_d, uh_q, if_d, if_q = firmware.voltage_estimate(
        i_d, i_q, i_d, i_q, w_e, w_bw, 1 - math.exp(-w_bw * TS), R, LD, LQ, PSI, 100.0
    )
    assert (uh_d, uh_q) == pytest.approx((R * i_d - w_e * LQ * i_q, R * i_q + w_e * (LD * i_d + PSI)))
    assert (if_d, if_q) == (i_d, i_q)
    # a step of i*: G_cl moves if by the exact first-order fraction 1 - exp(-w_bw T_s)
    _, _, if_d, _ = firmware.voltage_estimate(
        1.0, 0.0, 0.0, 0.0, 0.0, w_bw, 1 - math.exp(-w_bw * TS), R, LD, LQ, PSI, 100.0
    )
    assert if_d == pytest.approx(1 - math.exp(-w_bw * TS))


def test_field_weakening_integrates_clamps_and_respects_the_current_limit():
    # |u| above target: delta i_d goes negative by gain (|u| - target); i_q cut to the current circle
    did, id_ref, iq_ref = firmware.field_weakening(-10.0, 8.0, 2.0, 7.0, -50.0, -5.0, -113.0, 113.0**2)
    assert did == -12.0 and id_ref == -17.0 and iq_ref == pytest.approx(-math.sqrt(113.0**2 - 17.0**2))
    # below target it winds back, but never above 0; at 0 the feed-forward references are used
    assert firmware.field_weakening(-0.5, 6.0, 2.0, 7.0, -50.0, -5.0, 30.0, 113.0**2) == (0.0, -5.0, 30.0)
    assert firmware.field_weakening(-49.0, 9.0, 2.0, 7.0, -50.0, -5.0, 30.0, 113.0**2)[0] == -50.0


def test_torque_estimate_is_eq_20_with_nominal_parameters():
    i_d, i_q = -4.0, 33.0
    assert firmware.torque_estimate(i_d, i_q, 1.5 * NP * PSI, NP, LD, LQ) == pytest.approx(
        machine.torque(i_d, i_q, PSI, LD, LQ, NP), rel=1e-14
    )


# ---------------------------------------------------------------------------------------------
# DAQ frames: the emulator's bytes against the driver's decoder and encoder


def test_emulator_frames_decode_bit_exactly_with_the_driver_decoder():
    p, tab = scn.build(scn.load("paper-bench"))
    p = p.copy()
    p[ph.P_ALPHA_FS] = 60.0  # small enough that some samples clip (over-range flag)
    x = ph.new_state()
    ph.steady_state_init(x, p, 2.5, 2000.0, 12.0, tab)
    sp = op_setpoints(12.0, 2.5, 2000.0, theta_from_gamma_delta(math.radians(3), math.radians(280)))
    sp[ph.S_SYNC] = 1.0
    n, seq0 = 2048, 65536 - 700  # the sequence number wraps inside the block
    frames = np.zeros(n * ph.FRAME_BYTES, dtype=np.uint8)
    trace = np.zeros((n, ph.N_TRACE))
    ph.simulate(
        x,
        p,
        tab,
        sp,
        ph.NO_THETA_SCHEDULE,
        np.random.default_rng(3).standard_normal(n),
        256,
        seq0,
        frames,
        np.zeros((n // 256, ph.N_SUMMARY)),
        trace,
    )
    samples = FrameDecoder().feed(frames.tobytes())
    assert len(samples) == n and not samples.gap_before[1:].any()
    # what the wire should carry, computed here from the trace
    raw = np.clip(trace[:, ph.TR_ALPHA_MEAS] / p[ph.P_ALPHA_FS] * 32767.0, -32767.0, 32767.0)
    accel = (np.sign(raw) * np.floor(np.abs(raw) + 0.5)).astype(np.int64)
    angle = np.floor(trace[:, ph.TR_PHI_E] * 65536.0 / (2 * math.pi) + 0.5).astype(np.int64) & 0xFFFF
    over = np.abs(trace[:, ph.TR_ALPHA_MEAS] / p[ph.P_ALPHA_FS] * 32767.0) > 32767.0
    flags = ph.SYNC_FLAG | np.where(over, ph.OVER_RANGE_FLAG, 0)
    assert over.any() and not over.all()
    np.testing.assert_array_equal(np.round(samples.accel_fs * 32767.0).astype(np.int64), accel)
    np.testing.assert_array_equal(np.round(samples.angle_rad * 65536.0 / (2 * math.pi)).astype(np.int64), angle)
    np.testing.assert_array_equal(samples.flags, flags)
    seq = np.arange(seq0, seq0 + n)
    assert encode_frames(seq, angle, accel, flags) == frames.tobytes()
