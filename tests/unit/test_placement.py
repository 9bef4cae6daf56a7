"""Placement from theta* curves (service/maps/placement.py) against closed forms: the drive's interpolation
between two breakpoints, the predicted LUT-mode suppression 20 log10 |theta*| / |theta_lut - theta*| (eq. 8),
and the bisection's choices."""

from __future__ import annotations

import cmath
import math

import pytest

from drivers.lut_image import between
from service.maps.lut_export import image_bytes
from service.maps.placement import (
    PLACE_MARGIN_DB,
    candidate_cells,
    cells_to_measure,
    first_candidates,
    judge_candidates,
    midpoints,
    place,
    predicted_db,
    worst_db,
)


def test_midpoints_stop_where_the_halves_would_be_narrower_than_the_axis_step():
    assert midpoints([1000.0, 1400.0, 1420.0, 1435.0], "speed_rpm") == [1200.0, 1410.0]
    assert midpoints([1.0, 1.25, 2.0], "torque_nm") == [1.125, 1.625]
    assert midpoints([1.0, 1.2], "torque_nm") == []


def test_candidate_lines_add_every_cell_of_the_grown_full_grid_and_only_those():
    axes = {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1400.0], "udc_v": [12.0, 24.0]}
    cells = candidate_cells(axes, {"torque_nm": [1.5], "speed_rpm": [1200.0]})
    assert len(cells) == 3 * 3 * 2 - 2 * 2 * 2
    assert (1.5, 1200.0, 24.0) in cells and (1.0, 1000.0, 12.0) not in cells
    assert first_candidates(axes) == {"torque_nm": [1.5], "speed_rpm": [1200.0]}


def test_the_drives_interpolation_is_linear_in_cartesian_and_in_gamma_and_delta_in_polar():
    a, b = complex(0.02, 0.01), complex(-0.01, 0.03)
    assert between(a, b, 1000.0, 1400.0, 1100.0, "cartesian") == pytest.approx(0.75 * a + 0.25 * b, abs=1e-7)
    pa, pb = cmath.rect(0.02, 0.3), cmath.rect(0.04, 0.9)
    # the LUT stores theta = gamma (cos delta, -sin delta): gamma and delta each linear between the breakpoints
    assert between(pa, pb, 0.0, 1.0, 0.5, "polar") == pytest.approx(cmath.rect(0.03, 0.6), abs=1e-7)


def test_predicted_suppression_is_the_relative_error_in_db():
    assert predicted_db(complex(0.05, 0.0), complex(0.0505, 0.0)) == pytest.approx(40.0, abs=1e-9)
    assert predicted_db(complex(0.05, 0.0), complex(0.05, 0.0)) == math.inf
    assert predicted_db(complex(0.05, 0.0), complex(-0.05, 0.0)) == pytest.approx(20 * math.log10(0.5))


def _field(curvature: float):
    """theta*(T, n) = 0.05 + j 0.01 (n - 1000)/400 + curvature (n - 1000)^2: cartesian interpolation between n_a and
    n_b misses it at the midpoint by curvature (n_b - n_a)^2 / 4 exactly."""
    return lambda t, n: complex(0.05 + curvature * (n - 1000.0) ** 2, 0.01 * (n - 1000.0) / 400.0) * (1 + 0.1 * t)


def test_a_candidate_is_judged_by_its_worst_cell_with_the_closed_form_midpoint_error():
    axes = {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1400.0], "udc_v": [12.0]}
    f = _field(1e-7)
    cands = {"torque_nm": [1.5], "speed_rpm": [1200.0]}
    grid = {(t, n, 12.0) for t in (1.0, 1.5, 2.0) for n in (1000.0, 1200.0, 1400.0)}
    thetas = {c: f(c[0], c[1]) for c in grid}
    judged = judge_candidates(axes, cands, thetas, "cartesian")
    # along speed at each torque row: error 1e-7 * 400^2 / 4 = 4e-3 (times the row's scale, as theta itself)
    expected = min(20 * math.log10(abs(f(t, 1200.0)) / (4e-3 * (1 + 0.1 * t))) for t in (1.0, 2.0))
    assert len(judged["speed_rpm"][1200.0]) == 2  # a cell per torque row
    assert min(judged["speed_rpm"][1200.0]) == pytest.approx(expected, abs=1e-3)
    assert min(judged["torque_nm"][1.5]) > 200.0  # linear in torque: exact to rounding
    assert worst_db(judged)["speed_rpm"] == pytest.approx(expected, abs=1e-3)
    del thetas[(1.0, 1200.0, 12.0)], thetas[(2.0, 1200.0, 12.0)]
    assert judge_candidates(axes, cands, thetas, "cartesian")["speed_rpm"][1200.0] == []  # no evidence


def test_place_keeps_what_misses_the_target_with_its_margin_most_cells_per_byte_first_within_the_bytes():
    axes = {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1400.0, 1800.0], "udc_v": [12.0]}
    bar = 30.0 + PLACE_MARGIN_DB
    judged = {
        "torque_nm": {1.5: [bar + 1.0, bar + 3.0, bar + 2.0]},  # holds with the margin: dropped, its interval settled
        # 1200: one cell of two short, far; 1600: both cells short, barely; 2000: no evidence
        "speed_rpm": {1200.0: [20.0, bar + 5.0], 1600.0: [bar - 1.0, bar - 2.0], 2000.0: []},
    }
    kept, following, reasons = place(axes, judged, 30.0, None)
    assert kept == {"torque_nm": [], "speed_rpm": [1200.0, 1600.0]}
    # the torque interval settled at 1000, 1400, 1800 rpm is judged again at the speeds just kept
    assert following == {"torque_nm": [1.5], "speed_rpm": [1100.0, 1300.0, 1500.0, 1700.0]}
    assert reasons == []
    one_more = image_bytes({**axes, "speed_rpm": [1000.0, 1200.0, 1400.0, 1800.0]})
    kept, following, reasons = place(axes, judged, 30.0, one_more)
    assert kept["speed_rpm"] == [1600.0]  # two short cells for the line's bytes beat one; 1200 would not fit
    assert len(reasons) == 1 and "1200" in reasons[0] and str(one_more) in reasons[0]


def test_an_axis_is_judged_again_where_the_other_axis_grew_and_only_unmeasured_cells_are_measured():
    """Torque 1.5 held at the first speeds; a speed kept later re-opens it, and the next round measures the grid's
    new cells and the candidates' lines there, never a cell measured before nor the crossing of two candidates."""
    axes = {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1400.0, 1800.0], "udc_v": [12.0]}
    bar = 30.0 + PLACE_MARGIN_DB
    kept, following, _ = place(axes, {"torque_nm": {}, "speed_rpm": {1600.0: [bar - 5.0, bar - 5.0]}}, 30.0, None)
    assert kept == {"torque_nm": [], "speed_rpm": [1600.0]} and following["torque_nm"] == [1.5]
    # nothing kept on the speed axis: a settled torque interval stays settled
    _, quiet, _ = place(axes, {"torque_nm": {}, "speed_rpm": {1600.0: [bar + 5.0, bar + 5.0]}}, 30.0, None)
    assert quiet == {"torque_nm": [], "speed_rpm": []}

    grown = {**axes, "speed_rpm": [1000.0, 1400.0, 1600.0, 1800.0]}
    measured = {(t, n, 12.0) for t in (1.0, 1.5, 2.0) for n in (1000.0, 1400.0, 1800.0)} | {(1.0, 1600.0, 12.0)}
    cells = cells_to_measure(grown, following, measured)
    # the grid's new cell (2 Nm at 1600), the 1.5 Nm line at the new speed, the speed candidates' lines (1500, 1700)
    # at the torque rows; not 1.5 Nm x 1500/1700 rpm (two candidates cross) and not what was measured
    assert cells == sorted(
        [(2.0, 1600.0, 12.0), (1.5, 1600.0, 12.0)] + [(t, n, 12.0) for t in (1.0, 2.0) for n in (1500.0, 1700.0)]
    )
    assert cells_to_measure(grown, {}, measured | {(2.0, 1600.0, 12.0)}) == []
