"""Numerics against closed-form answers (not against their own output)."""

import cmath
import math

import numpy as np
import pytest

from service.model.harmonic import electrical_frequency_hz, phasor, whole_period_samples
from service.model.operating_point import OperatingPoint, nominal_steady_state
from service.model.secondary_path import (
    g_salpha,
    gamma_delta,
    model_secondary_path,
    s_matrix,
    theta_complex,
    theta_from_gamma_delta,
)
from service.settings import load_settings
from tests.support.operating_points import OP1_POINT


@pytest.fixture
def settings():
    return load_settings(environ={})


def test_gamma_delta_eq21_22_round_trip():
    # eq. 21-22: gamma = |theta|, delta = -atan2(theta_sin, theta_cos)
    gamma, delta = gamma_delta(0.0, -0.05)
    assert gamma == pytest.approx(0.05)
    assert math.degrees(delta) == pytest.approx(90.0)
    tc, ts = theta_from_gamma_delta(math.radians(3), math.radians(280))
    g, d = gamma_delta(tc, ts)
    assert math.degrees(g) == pytest.approx(3.0) and math.degrees(d) == pytest.approx(280.0)
    # v_inj = x^T theta = gamma cos(h phi + delta) for every phi
    phi = np.linspace(0, 2 * np.pi, 50)
    h = 6
    assert np.allclose(
        tc * np.cos(h * phi) + ts * np.sin(h * phi), math.radians(3) * np.cos(h * phi + math.radians(280))
    )


def test_s_matrix_matches_complex_form():
    s = complex(-0.8, 1.1)
    theta = np.array([0.01, -0.03])
    a = s_matrix(s) @ theta
    big_a = s * theta_complex(*theta)
    assert a[0] == pytest.approx(big_a.real) and a[1] == pytest.approx(-big_a.imag)


def test_steady_state_base_speed_closed_form(settings):
    m = settings.motor
    op = OP1_POINT  # 2.5 Nm, 2000 rpm, 12 V
    ss = nominal_steady_state(op, m)
    w = 2000 / 60 * 2 * math.pi * 4
    iq = 2.5 / (1.5 * 4 * m.psi_p_vs)
    assert not ss.field_weakening
    assert ss.i_q_a == pytest.approx(iq)
    assert ss.u_d_v == pytest.approx(-w * m.l_q_h * iq)
    assert ss.u_q_v == pytest.approx(m.r_s_ohm * iq + w * m.psi_p_vs)


def test_steady_state_field_weakening_sits_on_the_voltage_limit(settings):
    ss = nominal_steady_state(OperatingPoint(torque_nm=1.3, speed_rpm=3000, udc_v=12), settings.motor)
    assert ss.field_weakening and ss.i_d_a < 0
    assert ss.u_magnitude_v == pytest.approx(12 / math.sqrt(3), rel=1e-6)


def test_secondary_path_closed_form_surface_magnets(settings):
    """eq. 14-20 for L_d = L_q = L written out by hand:
    i_q/v_inj = (w_e u_q + (s + R/L) u_d) / (L ((s + R/L)^2 + w_e^2)), torque = k_T i_q."""
    m, c, mech = settings.motor, settings.control, settings.mechanics
    op = OP1_POINT  # 2.5 Nm, 2000 rpm, 12 V
    ss = nominal_steady_state(op, m)
    h = 6
    w_e = ss.omega_e_rad_s
    s = 1j * h * w_e
    L, a = m.l_d_h, m.r_s_ohm / m.l_d_h
    iq_per_rad = (w_e * ss.u_q_v + (s + a) * ss.u_d_v) / (L * ((s + a) ** 2 + w_e**2))
    torque_per_rad = 1.5 * m.pole_pairs * m.psi_p_vs * iq_per_rad * cmath.exp(-s * c.delay_periods / c.control_rate_hz)
    z, p = mech.zero_rad_s, complex(mech.pole_re_rad_s, mech.pole_im_rad_s)
    gsa = (1 / mech.inertia_kg_m2) * (abs(p) ** 2 / -z) * (s - z) / ((s - p) * (s - p.conjugate()))
    expected = gsa * torque_per_rad / settings.daq.accel_full_scale_rad_s2
    assert model_secondary_path(settings, op, h) == pytest.approx(expected, rel=1e-9)


def test_g_salpha_dc_gain_and_resonance():
    assert g_salpha(0j, 2e-3, -35954, -19.6, 6746.2) == pytest.approx(500.0)  # 1/J
    at_resonance = abs(g_salpha(1j * 6746.2, 2e-3, -35954, -19.6, 6746.2))
    assert at_resonance > 100 * 500.0  # lightly damped pole pair (zeta ~ 0.003)


@pytest.mark.parametrize("speed_rpm", [2000.0, 1234.5, 3100.0])
def test_phasor_whole_periods_exact(speed_rpm):
    fs, h, npp = 16000.0, 6, 4
    w_e = speed_rpm / 60 * 2 * math.pi * npp
    k = np.arange(8000)
    phi = (w_e * k / fs + 0.3) % (2 * math.pi)
    alpha = 0.07 * np.cos(h * phi) - 0.02 * np.sin(h * phi) + 0.01 * np.cos(2 * h * phi) + 0.05 * np.cos(phi)
    p = phasor(alpha, phi, h, 42)  # 7 whole electrical turns: every integer order averages out
    # whole-period window: other orders average out to the discretisation error of the window end
    assert p.a_c == pytest.approx(0.07, abs=3e-4) and p.a_s == pytest.approx(-0.02, abs=3e-4)
    n = whole_period_samples(phi, h, 42)
    assert abs(h * (np.unwrap(phi)[n] - np.unwrap(phi)[0]) - 2 * math.pi * 42) <= h * w_e / fs / 2 + 1e-9
    assert electrical_frequency_hz(phi, fs) == pytest.approx(w_e / (2 * math.pi), rel=1e-9)


def test_electrical_frequency_across_daq_gaps_uses_contiguous_runs_only():
    # 6000 rpm, 4 pole pairs: 400 Hz electrical, 40 samples per turn at 16 kHz; gaps of 25 samples
    # (more than half a turn) make the angle's step across them ambiguous
    fs, f_e = 16000.0, 400.0
    k = np.arange(2000)
    keep = np.ones(len(k), bool)
    for start in (300, 900, 1500):
        keep[start : start + 25] = False  # frames lost or dropped for a bad CRC
    index = k[keep]
    phi = (2 * math.pi * f_e * index / fs + 1.0) % (2 * math.pi)
    gap_before = np.zeros(len(index), bool)
    gap_before[1:] = np.diff(index) > 1
    assert gap_before.sum() == 3
    assert electrical_frequency_hz(phi, fs, gap_before) == pytest.approx(f_e, rel=1e-9)
    # naively joined, the lost time is missed and each step across a gap wraps the wrong way
    assert abs(electrical_frequency_hz(phi, fs) - f_e) > 0.01 * f_e
    # nothing contiguous: no speed, rather than a made-up one
    with pytest.raises(ValueError, match="contiguous"):
        electrical_frequency_hz(phi[:3], fs, np.array([False, True, True]))


def test_phasor_refuses_short_record():
    phi = np.linspace(0, 1, 100)
    with pytest.raises(ValueError, match="fewer than"):
        phasor(np.zeros(100), phi, 6, 10)


def test_secondary_path_with_current_loop_closed_form(settings):
    """Closed current loop for L_d = L_q = L, derived by hand: with D = L (s + R/L) + e^{-sT_d} (K_p + K_i/s),
    K_p = w_bw L, K_i = w_bw R, the q current per rad of injection is (L w_e u_q + D u_d) / (D^2 + L^2 w_e^2)."""
    m, c, mech = settings.motor, settings.control, settings.mechanics
    op = OP1_POINT  # 2.5 Nm, 2000 rpm, 12 V
    ss = nominal_steady_state(op, m)
    h, w_e, L, R = 6, ss.omega_e_rad_s, m.l_d_h, m.r_s_ohm
    s = 1j * h * w_e
    delay = cmath.exp(-s * c.delay_periods / c.control_rate_hz)
    w_bw = 2 * math.pi * c.bandwidth_hz
    d = L * (s + R / L) + delay * (w_bw * L + w_bw * R / s)
    iq_per_rad = (L * w_e * ss.u_q_v + d * ss.u_d_v) / (d**2 + (L * w_e) ** 2)
    z, p = mech.zero_rad_s, complex(mech.pole_re_rad_s, mech.pole_im_rad_s)
    gsa = (1 / mech.inertia_kg_m2) * (abs(p) ** 2 / -z) * (s - z) / ((s - p) * (s - p.conjugate()))
    expected = gsa * 1.5 * m.pole_pairs * m.psi_p_vs * iq_per_rad * delay / settings.daq.accel_full_scale_rad_s2
    assert model_secondary_path(settings, op, h, current_loop=True) == pytest.approx(expected, rel=1e-9)
    # the loop turns S by tens of degrees at 800 Hz: what a drive without decoupling shows
    turn = math.degrees(cmath.phase(expected / model_secondary_path(settings, op, h)))
    assert 10 < abs(turn) < 60
