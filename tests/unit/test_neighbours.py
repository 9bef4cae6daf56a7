"""Neighbour priors (service/maps/neighbours.py) on their own: which stored result a new point starts
from, against distances and interpolations worked out by hand (theta from gamma and delta, eq. 21-22),
and where the secondary path S may come from (the same speed and DC-link voltage only)."""

from __future__ import annotations

import math

import pytest

from service.maps import neighbours
from service.maps.neighbours import prior_from_neighbours
from service.model.operating_point import OperatingPoint

AXES = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 2000.0, 3000.0], "udc_v": [12.0]}
S_A = [[0.8, -0.6], [0.6, 0.8]]
S_B = [[1.0, 0.2], [-0.2, 1.0]]


def theta(gamma_deg: float, delta_deg: float) -> tuple[float, float]:
    """theta (rad) of gamma, delta: theta_cos = gamma cos delta, theta_sin = -gamma sin delta."""
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return g * math.cos(d), -g * math.sin(d)


def row(
    t: float, n: float, th: tuple[float, float] | None, status: str = "ok", u: float = 12.0, details: dict | None = None
) -> dict:
    """A stored result row as the sweep's history gives it."""
    return {
        "torque_nm": t,
        "speed_rpm": n,
        "udc_v": u,
        "status": status,
        "theta_cos": None if th is None else th[0],
        "theta_sin": None if th is None else th[1],
        "detail": {"details": details or {}},
    }


def op(t: float, n: float, u: float = 12.0) -> OperatingPoint:
    return OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u)


def test_no_ok_result_gives_no_prior():
    rows = [
        row(1.0, 1000.0, theta(3, 280), status="failed"),
        row(2.0, 1000.0, theta(3, 280), status="below_target"),
        row(3.0, 1000.0, None),
    ]
    assert prior_from_neighbours(op(2.0, 2000.0), rows, AXES) is None
    assert prior_from_neighbours(op(2.0, 2000.0), [], AXES) is None


def test_the_only_ok_neighbour_is_the_prior():
    a = theta(3.0, 280.0)
    prior = prior_from_neighbours(op(2.0, 2000.0), [row(1.0, 1000.0, a)], AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(a)
    assert prior.s_matrix is None  # 1000 rpm: not the new point's speed
    assert prior.source == "neighbour 1 Nm / 1000 rpm / 12 V"


def test_the_nearest_neighbour_is_nearest_in_axes_scaled_by_their_span():
    """From (2 Nm, 2000 rpm): 1 Nm away is half the torque span (2 Nm), 600 rpm only 0.3 of the speed
    span (2000 rpm): the speed neighbour is nearer, though 600 > 1 in raw units."""
    near, far = theta(4.0, 300.0), theta(3.0, 280.0)
    rows = [row(1.0, 2000.0, far), row(2.0, 2600.0, near)]
    prior = prior_from_neighbours(op(2.0, 2000.0), rows, AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(near)
    assert prior.source.startswith("neighbour 2 Nm / 2600 rpm / 12 V")


def test_results_that_are_not_ok_are_never_a_prior_however_near():
    ok = theta(3.0, 280.0)
    rows = [
        row(2.0, 2000.0, theta(9.0, 10.0), status="below_target"),
        row(2.0, 2000.0, theta(9.0, 10.0), status="failed"),
        row(3.0, 3000.0, ok),
    ]
    prior = prior_from_neighbours(op(2.0, 2000.0), rows, AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(ok)


def test_s_comes_from_the_nearest_ok_cell_at_the_same_speed_and_voltage_theta_from_the_nearest_anywhere():
    """theta from 2 Nm / 2600 rpm (0.3 span away), S from 1 Nm / 2000 rpm (0.5 away, the same speed):
    S turns across the shaft resonance in speed, theta* does not."""
    rows = [
        row(1.0, 2000.0, theta(3.0, 280.0), details={"s_matrix": S_A}),
        row(2.0, 2600.0, theta(4.0, 300.0), details={"s_matrix": S_B}),
        row(3.0, 2000.0, theta(3.0, 280.0), u=24.0, details={"s_matrix": S_B}),
    ]
    prior = prior_from_neighbours(op(2.0, 2000.0), rows, {**AXES, "udc_v": [12.0, 24.0]})
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(theta(4.0, 300.0))
    assert prior.s_matrix == ((0.8, -0.6), (0.6, 0.8))
    assert prior.source == "neighbour 2 Nm / 2600 rpm / 12 V, S from 1 Nm"


def test_a_refined_s_is_preferred_and_a_cell_without_s_gives_none():
    refined = [[0.9, -0.5], [0.5, 0.9]]
    rows = [row(1.0, 2000.0, theta(3.0, 280.0), details={"s_matrix": S_A, "s_matrix_refined": refined})]
    assert prior_from_neighbours(op(2.0, 2000.0), rows, AXES).s_matrix == ((0.9, -0.5), (0.5, 0.9))
    rows = [row(1.0, 2000.0, theta(3.0, 280.0))]
    prior = prior_from_neighbours(op(2.0, 2000.0), rows, AXES)
    assert prior.s_matrix is None and "S from" not in prior.source


@pytest.mark.parametrize("interpolation", ["cartesian", "polar"])
def test_between_ok_cells_on_both_sides_the_prior_is_what_the_lut_would_inject_there(monkeypatch, interpolation):
    """At 1.5 Nm between 1 Nm and 3 Nm: weights 3/4 and 1/4. Cartesian: the weighted mean of the thetas;
    polar (equal gammas): gamma 3 deg and delta a quarter of the way from 280 to 300 deg."""
    monkeypatch.setattr(neighbours, "DEFAULT_INTERPOLATION", interpolation)
    a, b = theta(3.0, 280.0), theta(3.0, 300.0)
    rows = [row(1.0, 2000.0, a), row(3.0, 2000.0, b)]
    prior = prior_from_neighbours(op(1.5, 2000.0), rows, {**AXES, "torque_nm": [1.0, 1.5, 3.0]})
    expected = (
        (0.75 * a[0] + 0.25 * b[0], 0.75 * a[1] + 0.25 * b[1]) if interpolation == "cartesian" else theta(3.0, 285.0)
    )
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(expected)
    assert prior.source.startswith(f"interpolated ({interpolation})") and "torque_nm between 1 and 3" in prior.source


def test_a_refinement_cell_between_the_old_axis_values_interpolates_too(monkeypatch):
    """A new cell at 2.5 Nm, not on the sweep's axes (1, 2, 3 Nm): midway between 2 and 3 Nm."""
    monkeypatch.setattr(neighbours, "DEFAULT_INTERPOLATION", "cartesian")
    a, b = theta(2.0, 270.0), theta(4.0, 290.0)
    rows = [row(2.0, 3000.0, a), row(3.0, 3000.0, b)]
    prior = prior_from_neighbours(op(2.5, 3000.0), rows, AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(((a[0] + b[0]) / 2, (a[1] + b[1]) / 2))
    assert "torque_nm between 2 and 3" in prior.source


def test_one_side_only_holds_the_nearest_instead_of_extrapolating():
    a, b = theta(2.0, 270.0), theta(4.0, 290.0)
    rows = [row(1.0, 1000.0, a), row(2.0, 1000.0, b)]
    prior = prior_from_neighbours(op(3.0, 1000.0), rows, AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(b)
    assert prior.source.startswith("neighbour 2 Nm / 1000 rpm / 12 V")
