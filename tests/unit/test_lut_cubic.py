"""The drive's cubic interpolation (drivers/lut_image.py, mode 2) against closed forms: a cubic Hermite along speed
whose slopes are the non-uniform three-point derivative reproduces any quadratic of speed exactly between inner
breakpoints (that derivative is exact for a quadratic, and a Hermite with exact end slopes is exact for a cubic);
across torque and U_dc it is multilinear; a corner without an entry or off behaves as in the linear modes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers import lut_image
from service.maps.placement import judge_candidates

SPEED = [1000.0, 1300.0, 1450.0, 1900.0, 2000.0, 2600.0]  # non-uniform
TORQUE = [1.0, 3.0]
UDC = [12.0]


def quadratic(t: float, n: float) -> complex:
    """theta* (rad) quadratic in speed, linear in torque: a loop's piece (both components bend)."""
    x = (n - 1800.0) / 1000.0
    return complex(0.02 - 0.01 * x - 0.015 * x * x, -0.01 + 0.02 * x + 0.01 * x * x) * (0.5 + 0.25 * t)


def image(flags=None) -> lut_image.Lut:
    thetas = np.array([[[quadratic(t, n) for t in TORQUE] for n in SPEED] for _ in UDC])
    blob = lut_image.encode(6, TORQUE, SPEED, UDC, thetas.real, thetas.imag, flags, map_id=9, interpolation="cubic")
    return lut_image.decode(blob)


def test_a_quadratic_of_speed_is_held_exactly_between_inner_breakpoints_and_linearly_across_torque():
    lut = image()
    assert lut.interpolation == "cubic"
    for n in np.linspace(SPEED[1], SPEED[-2], 97):  # the end intervals take the secant at the axis end
        for t in (1.0, 1.7, 3.0):
            c, s = lut.theta(t, float(n), 12.0)
            # float32 cells: ~1e-9 rad
            assert abs(complex(c, s) - quadratic(t, float(n))) < 1e-8, (t, n)
    # at a breakpoint the cell itself; beyond the ends the end's
    assert complex(*lut.theta(1.0, 1450.0, 12.0)) == pytest.approx(quadratic(1.0, 1450.0), abs=1e-8)
    assert complex(*lut.theta(3.0, 9000.0, 12.0)) == pytest.approx(quadratic(3.0, 2600.0), abs=1e-8)


def test_the_linear_modes_miss_the_same_quadratic_by_its_curvature():
    """Closed form: the chord of a quadratic q lies q'' h^2 / 8 off it midway."""
    thetas = np.array([[[quadratic(t, n) for t in TORQUE] for n in SPEED] for _ in UDC])
    lut = lut_image.decode(
        lut_image.encode(6, TORQUE, SPEED, UDC, thetas.real, thetas.imag, map_id=9, interpolation="cartesian")
    )
    a, b = 1450.0, 1900.0
    second = complex(-0.03, 0.02) * 0.75 / 1000.0**2  # q'' at 1 Nm, rad / rpm^2
    miss = complex(*lut.theta(1.0, (a + b) / 2, 12.0)) - quadratic(1.0, (a + b) / 2)
    assert miss == pytest.approx(second * (b - a) ** 2 / 8, abs=1e-8)


def test_a_neighbour_without_an_entry_or_off_leaves_the_secant_and_an_off_corner_gives_nothing():
    flags = np.full((1, len(SPEED), len(TORQUE)), lut_image.FLAG_OK)
    flags[0, 1, 0] = lut_image.FLAG_NONE  # 1300 rpm, 1 Nm: no entry
    flags[0, 4, 0] = lut_image.FLAG_OFF  # 2000 rpm, 1 Nm: injection off
    lut = image(flags)
    # 1450..1900 at 1 Nm: both neighbours out, so both slopes are the secant: linear there
    a, b = quadratic(1.0, 1450.0), quadratic(1.0, 1900.0)
    mid = complex(*lut.theta(1.0, 1675.0, 12.0))
    assert mid == pytest.approx((a + b) / 2, abs=1e-8)
    # an interval with the off corner: exactly nothing, at any torque where that row weighs
    assert lut.theta(1.0, 1950.0, 12.0) == (0.0, 0.0)
    assert lut.theta(2.0, 1950.0, 12.0) == (0.0, 0.0)
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
    second = complex(-0.03, 0.02) * 0.75 / 1000.0**2
    expected = 20 * math.log10(abs(quadratic(1.0, 1600.0)) / abs(second * 400.0**2 / 8))
    assert linear[0] == pytest.approx(expected, abs=0.01)
