"""The envelope model (service.model.operating_point.torque_envelope, service.model.limits.check_envelope)
against closed-form answers: with R_s -> 0 and L_d = L_q = L, the voltage limit |u_dq| <= U is a circle of radius
U / (omega_e L) around i_d = -psi_p / L, the current limit a circle of radius I around 0, and T = k_T i_q."""

from __future__ import annotations

import math

import pytest

from service.model.limits import EnvelopeError, LimitError, check_envelope, check_point, torque_departure
from service.model.operating_point import OperatingPoint, field_weakening_onset, torque_envelope
from service.settings import MotorSettings, load_settings

PSI, L, I_MAX, NP = 7.0e-3, 20e-6, 113.0, 4
IDEAL = MotorSettings(pole_pairs=NP, r_s_ohm=1e-12, l_d_h=L, l_q_h=L, psi_p_vs=PSI, i_max_a=I_MAX)
K_T = 1.5 * NP * PSI  # Nm/A
U = 0.95 * 12.0 / math.sqrt(3.0)  # V, the firmware's limit at 12 V


def rpm(omega_e: float) -> float:
    return omega_e / NP * 60.0 / (2.0 * math.pi)


def test_below_base_speed_the_current_limit_binds():
    corner = U / math.hypot(L * I_MAX, PSI)  # rad/s: (omega L I)^2 + (omega psi)^2 = U^2
    for n in (100.0, 1000.0, 0.99 * rpm(corner)):
        env = torque_envelope(n, 12.0, IDEAL, 0.95)
        assert env.holds_currents and env.limited_by == "current"
        assert env.max_torque_nm == pytest.approx(K_T * I_MAX, rel=1e-6)


@pytest.mark.parametrize("n", [2500.0, 2800.0, 3100.0])
def test_above_base_speed_the_circles_intersect(n):
    omega = n / 60.0 * 2.0 * math.pi * NP
    # i_d^2 + i_q^2 = I^2 and (i_d + psi/L)^2 + i_q^2 = (U / (omega L))^2
    i_d = ((U / (omega * L)) ** 2 - I_MAX**2 - (PSI / L) ** 2) / (2.0 * PSI / L)
    expected = K_T * math.sqrt(I_MAX**2 - i_d**2)
    env = torque_envelope(n, 12.0, IDEAL, 0.95)
    assert env.holds_currents and env.limited_by == "voltage"
    assert env.max_torque_nm == pytest.approx(expected, rel=1e-5)


def test_beyond_full_field_weakening_the_currents_are_not_held():
    limit_rpm = rpm(U / (PSI - L * I_MAX))  # omega (psi - L I) = U
    env = torque_envelope(0.999 * limit_rpm, 12.0, IDEAL, 0.95)
    assert env.holds_currents and env.max_torque_nm < 0.1
    assert env.max_speed_rpm == pytest.approx(limit_rpm, rel=1e-6)
    beyond = torque_envelope(1.001 * limit_rpm, 12.0, IDEAL, 0.95)
    assert not beyond.holds_currents and beyond.max_torque_nm == 0.0


def test_a_field_that_weakens_to_zero_holds_at_any_speed():
    strong = MotorSettings(pole_pairs=NP, r_s_ohm=1e-12, l_d_h=1e-4, l_q_h=1e-4, psi_p_vs=PSI, i_max_a=I_MAX)
    env = torque_envelope(30000.0, 12.0, strong, 0.95)
    assert env.holds_currents and env.max_speed_rpm is None and env.max_torque_nm > 0


def test_the_onset_of_a_reachable_torque_is_within_the_envelope():
    # below its field-weakening onset a torque needs no field weakening: the envelope holds it
    for torque in (1.0, 2.5, 4.0):
        onset = field_weakening_onset(torque, 12.0, IDEAL, 0.95)
        assert torque_envelope(onset.speed_rpm, 12.0, IDEAL, 0.95).max_torque_nm >= torque - 1e-6


def test_refusals_name_the_reason_and_the_override_never_passes_the_hard_limits():
    s = load_settings(environ={})
    # the points (limit 5 Nm, 6000 rpm, 12 V): the back-EMF beyond the DC link
    for torque, speed in ((-2.5, 5000), (2.5, 5000), (5.0, 6000)):
        with pytest.raises(EnvelopeError, match="back-EMF exceeds what the DC link holds") as exc:
            check_envelope(OperatingPoint(torque_nm=torque, speed_rpm=speed, udc_v=12), s)
        assert [f for f, _ in exc.value.problems] == ["speed_rpm"] and "up to 3266 rpm at 12 V" in str(exc.value)
        check_point(OperatingPoint(torque_nm=torque, speed_rpm=speed, udc_v=12), s, override_envelope_model=True)
    # past the voltage limit: 4 Nm at 2600 rpm reaches 2.58 Nm (the firmware's own most-torque point)
    with pytest.raises(EnvelopeError, match=r"holds at most 2\.58 Nm here \(the voltage limit 6\.58 V"):
        check_envelope(OperatingPoint(torque_nm=4.0, speed_rpm=2600, udc_v=12), s)
    # within the tolerance (20 %): 5 Nm at 500 rpm reaches 4.75 Nm at the current limit; the paper's OP2
    check_envelope(OperatingPoint(torque_nm=5.0, speed_rpm=500, udc_v=12), s)
    check_envelope(OperatingPoint(torque_nm=1.3, speed_rpm=3000, udc_v=12), s)
    # the override is for the model only: a hard limit still refuses, as a LimitError that is not EnvelopeError
    with pytest.raises(LimitError) as hard:
        check_point(OperatingPoint(torque_nm=6.0, speed_rpm=5000, udc_v=12), s, override_envelope_model=True)
    assert not isinstance(hard.value, EnvelopeError) and "exceeds the limit of 5 Nm" in str(hard.value)


def test_a_torque_that_left_its_command_is_named():
    safety = load_settings(environ={}).safety
    assert torque_departure(2.5, 2.3, safety) is None  # within 0.5 Nm (20 %)
    assert torque_departure(0.5, 0.3, safety) is None  # within the 0.25 Nm floor
    assert "ran at -5.69 Nm" in torque_departure(-2.5, -5.69, safety)
    assert "ran at -5.30 Nm" in torque_departure(2.5, -5.3, safety)
    assert "no torque actual" in torque_departure(2.5, None, safety)
