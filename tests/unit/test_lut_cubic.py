"""The drive's cubic interpolation (drivers/lut_image.py, mode 2) against closed forms: a cubic Hermite whose slopes
are the non-uniform three-point derivative reproduces a quadratic exactly between inner breakpoints (that derivative
is exact for a quadratic, and a Hermite with exact end slopes is exact for a cubic); along speed in each row, then
across torque over the rows, so a product of quadratics in speed and torque is held exactly inside both axes; a
corner without an entry or off behaves as in the linear modes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers import lut_image
from service.maps.placement import judge_candidates

SPEED = [1000.0, 1300.0, 1450.0, 1900.0, 2000.0, 2600.0]  # non-uniform
TORQUE = [0.5, 1.0, 2.0, 2.5, 4.0]  # non-uniform
UDC = [12.0]


def quadratic(t: float, n: float) -> complex:
    """theta* (rad) quadratic in speed and in torque: a loop's piece (both components bend)."""
    x = (n - 1800.0) / 1000.0
    return complex(0.02 - 0.01 * x - 0.015 * x * x, -0.01 + 0.02 * x + 0.01 * x * x) * torque_factor(t)


def torque_factor(t: float) -> float:
    return 0.5 + 0.25 * t - 0.04 * t * t


def image(flags=None) -> lut_image.Lut:
    thetas = np.array([[[quadratic(t, n) for t in TORQUE] for n in SPEED] for _ in UDC])
    blob = lut_image.encode(6, TORQUE, SPEED, UDC, thetas.real, thetas.imag, flags, map_id=9, interpolation="cubic")
    return lut_image.decode(blob)


def test_quadratics_of_speed_and_torque_are_held_exactly_between_inner_breakpoints():
    lut = image()
    assert lut.interpolation == "cubic"
    for n in np.linspace(SPEED[1], SPEED[-2], 97):  # the end intervals take the secant at the axis end
        for t in np.linspace(TORQUE[1], TORQUE[-2], 13):
            c, s = lut.theta(t, float(n), 12.0)
            # float32 cells: ~1e-9 rad
            assert abs(complex(c, s) - quadratic(t, float(n))) < 1e-8, (t, n)
    # at a breakpoint the cell itself; beyond the ends the end's
    assert complex(*lut.theta(1.0, 1450.0, 12.0)) == pytest.approx(quadratic(1.0, 1450.0), abs=1e-8)
    assert complex(*lut.theta(4.0, 9000.0, 12.0)) == pytest.approx(quadratic(4.0, 2600.0), abs=1e-8)
    # the end intervals are not exact: the secant there (so the test above is not trivially true)
    assert abs(complex(*lut.theta(1.0, 1150.0, 12.0)) - quadratic(1.0, 1150.0)) > 1e-5


def test_the_linear_modes_miss_the_same_quadratic_by_its_curvature():
    """Closed form: the chord of a quadratic q lies q'' h^2 / 8 off it midway."""
    thetas = np.array([[[quadratic(t, n) for t in TORQUE] for n in SPEED] for _ in UDC])
    lut = lut_image.decode(
        lut_image.encode(6, TORQUE, SPEED, UDC, thetas.real, thetas.imag, map_id=9, interpolation="cartesian")
    )
    a, b = 1450.0, 1900.0
    second = complex(-0.03, 0.02) * torque_factor(1.0) / 1000.0**2  # q'' at 1 Nm, rad / rpm^2
    miss = complex(*lut.theta(1.0, (a + b) / 2, 12.0)) - quadratic(1.0, (a + b) / 2)
    assert miss == pytest.approx(second * (b - a) ** 2 / 8, abs=1e-8)


def test_a_neighbour_without_an_entry_or_off_leaves_the_secant_and_an_off_corner_gives_nothing():
    flags = np.full((1, len(SPEED), len(TORQUE)), lut_image.FLAG_OK)
    flags[0, 1, 1] = lut_image.FLAG_NONE  # 1300 rpm, 1 Nm: no entry
    flags[0, 4, 1] = lut_image.FLAG_OFF  # 2000 rpm, 1 Nm: injection off
    lut = image(flags)
    # 1450..1900 at 1 Nm: both neighbours out, so both slopes are the secant: linear there
    a, b = quadratic(1.0, 1450.0), quadratic(1.0, 1900.0)
    mid = complex(*lut.theta(1.0, 1675.0, 12.0))
    assert mid == pytest.approx((a + b) / 2, abs=1e-8)
    # an interval with the off corner: exactly nothing, at any torque where that row weighs
    assert lut.theta(1.0, 1950.0, 12.0) == (0.0, 0.0)
    assert lut.theta(0.7, 1950.0, 12.0) == (0.0, 0.0)
    # with the corner without an entry: a linear blend towards theta 0 (as cartesian)
    f = (1350.0 - 1300.0) / 150.0
    assert complex(*lut.theta(1.0, 1350.0, 12.0)) == pytest.approx(f * quadratic(1.0, 1450.0), abs=1e-8)


def test_the_placement_predicts_a_speed_candidate_by_the_drives_cubic():
    """A candidate between two speed breakpoints of a quadratic theta*: cubic predicts it exactly (inner interval),
    polar and cartesian by the curvature's miss."""
    axes = {"torque_nm": [1.0], "speed_rpm": [1000.0, 1400.0, 1800.0, 2200.0], "udc_v": [12.0]}
    thetas = {(1.0, n, 12.0): quadratic(1.0, n) for n in (1000.0, 1400.0, 1600.0, 1800.0, 2200.0)}
    cubic = judge_candidates(axes, {"speed_rpm": [1600.0]}, thetas, "cubic")["speed_rpm"][1600.0]
    linear = judge_candidates(axes, {"speed_rpm": [1600.0]}, thetas, "cartesian")["speed_rpm"][1600.0]
    assert cubic[0] > 100.0  # float64: the quadratic exactly (inf would be exact to the bit)
    second = complex(-0.03, 0.02) * torque_factor(1.0) / 1000.0**2
    expected = 20 * math.log10(abs(quadratic(1.0, 1600.0)) / abs(second * 400.0**2 / 8))
    assert linear[0] == pytest.approx(expected, abs=0.01)


def test_the_placement_predicts_a_torque_candidate_by_the_drives_cubic_across_torque():
    axes = {"torque_nm": [0.5, 1.0, 2.0, 2.5], "speed_rpm": [1800.0], "udc_v": [12.0]}
    thetas = {(t, 1800.0, 12.0): quadratic(t, 1800.0) for t in (0.5, 1.0, 1.5, 2.0, 2.5)}
    cubic = judge_candidates(axes, {"torque_nm": [1.5]}, thetas, "cubic")["torque_nm"][1.5]
    linear = judge_candidates(axes, {"torque_nm": [1.5]}, thetas, "cartesian")["torque_nm"][1.5]
    assert cubic[0] > 100.0
    # the chord misses a quadratic by its curvature: -0.08 x 0.5^2 / 8 of theta*'s speed part
    miss = abs(quadratic(1.0, 1800.0) / torque_factor(1.0) * 0.08 * 1.0**2 / 8)
    assert linear[0] == pytest.approx(20 * math.log10(abs(quadratic(1.5, 1800.0)) / miss), abs=0.01)
