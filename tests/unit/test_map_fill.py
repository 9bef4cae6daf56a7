"""The fill rule (service/maps/fill.py) and the priors a sweep's second pass starts from
(service/maps/neighbours.py), against hand-worked values."""

from __future__ import annotations

import math

import pytest

from drivers.lut_image import DEFAULT_INTERPOLATION
from service.maps.build import build_map
from service.maps.fill import MEASURED_MIN_DB, NO_AUTHORITY_MIN_DB, blend, fill_cells
from service.maps.neighbours import prior_from_neighbours
from service.model.operating_point import OperatingPoint
from service.runs.plans import Grid, SweepPlan
from service.runs.sweep_run import second_pass_points

AXES = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 1500.0, 2500.0], "udc_v": [12.0]}


def theta(gamma_deg: float, delta_deg: float) -> tuple[float, float]:
    """theta from gamma and delta (delta = -atan2(theta_sin, theta_cos))."""
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return g * math.cos(d), -g * math.sin(d)


def cell(t, n, status="ok", th=(0.0, 0.0), db=45.0, u=12.0) -> dict:
    return {
        "torque_nm": t,
        "speed_rpm": n,
        "udc_v": u,
        "status": status,
        "theta_cos": th[0] if th is not None else None,
        "theta_sin": th[1] if th is not None else None,
        "suppression_db": db,
    }


def grid_of(fn) -> list[dict]:
    return [fn(t, n) for n in AXES["speed_rpm"] for t in AXES["torque_nm"]]


def test_ok_cells_are_never_filled():
    assert fill_cells(grid_of(lambda t, n: cell(t, n, th=theta(3, 280))), AXES) == {}


def test_a_below_target_cell_that_beat_the_harmonic_clearly_keeps_its_own_theta():
    own = theta(2.0, 100)

    def make(t, n):
        if (t, n) == (2.0, 1500.0):
            return cell(t, n, "below_target", own, db=MEASURED_MIN_DB + 4)
        return cell(t, n, th=theta(3, 280))

    fills = fill_cells(grid_of(make), AXES)
    f = fills[(2.0, 1500.0, 12.0)]
    assert (f.theta_cos, f.theta_sin) == own and f.source.startswith("measured")


class FillsOf:
    """Takes the fills build_map hands to storage (the map's other columns do not matter here)."""

    def create_map(self, *args, fills=None, **kwargs) -> int:
        self.fills = fills
        return 1


def test_a_second_attempt_that_ended_worse_leaves_the_fill_to_the_first_attempts_theta():
    """A sweep's second pass may start from a poor prior (interpolated across the field-weakening turn)
    and end worse than the first pass did: the cell's fill takes the theta that suppressed most."""
    first, second = theta(2.37, 250.6), theta(1.85, 261.7)
    rows = [
        {**cell(t, n, th=theta(3, 280)), "id": 10 + i}
        for i, (t, n) in enumerate((t, n) for n in AXES["speed_rpm"] for t in AXES["torque_nm"])
        if (t, n) != (2.0, 1500.0)
    ]
    attempt_1 = {**cell(2.0, 1500.0, "below_target", first, db=41.1), "id": 1, "detail": {}}
    attempt_2 = {**cell(2.0, 1500.0, "below_target", second, db=12.8), "id": 2, "detail": {}}
    storage = FillsOf()
    build_map(storage, AXES, rows + [attempt_2], 7, 6, "probe", "test", attempts=[attempt_1, attempt_2])
    f = storage.fills[(2.0, 1500.0, 12.0)]
    assert (f.theta_cos, f.theta_sin) == first
    assert "41.1 dB" in f.source and "attempt result 1" in f.source
    # the attempt an interlock discarded never counts
    discarded = {**attempt_1, "detail": {"discarded": "interlock"}}
    build_map(storage, AXES, rows + [attempt_2], 7, 6, "probe", "test", attempts=[discarded, attempt_2])
    f = storage.fills[(2.0, 1500.0, 12.0)]
    assert not f.source.startswith("measured")


def test_no_authority_needs_only_to_halve_the_harmonic():
    own = theta(15.0, 10)
    cells = [cell(1.0, 1000.0, "no_authority", own, db=NO_AUTHORITY_MIN_DB + 1), cell(2.0, 1000.0)]
    fills = fill_cells(cells, {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0], "udc_v": [12.0]})
    assert fills[(1.0, 1000.0, 12.0)].theta_cos == own[0]


def test_a_failed_cell_between_ok_cells_is_interpolated_by_position_cartesian():
    # speed line at 2 Nm: 1000 rpm has theta (a, 0), 2500 rpm (0, b); 1500 rpm lies at 1/3 of the interval
    lo, hi = (0.03, 0.0), (0.0, 0.06)

    def make(t, n):
        if t != 2.0:
            return cell(t, n, "failed", None)  # nothing on the torque axis
        return {1000.0: cell(t, n, th=lo), 1500.0: cell(t, n, "failed", None), 2500.0: cell(t, n, th=hi)}[n]

    f = fill_cells(grid_of(make), AXES)[(2.0, 1500.0, 12.0)]
    assert f.theta_cos == pytest.approx(0.03 * 2 / 3) and f.theta_sin == pytest.approx(0.06 / 3)
    assert "speed_rpm between 1000 and 2500" in f.source


def test_polar_keeps_gamma_and_turns_delta_along_the_shortest_arc():
    # 350 deg and 10 deg, same gamma: the polar midpoint is gamma at 0 deg (never 180); cartesian shrinks gamma
    a, b = theta(3.0, 350), theta(3.0, 10)
    mid = blend([(0.5, a), (0.5, b)], "polar")
    assert math.hypot(*mid) == pytest.approx(math.radians(3.0))
    assert math.degrees(-math.atan2(mid[1], mid[0])) == pytest.approx(0.0, abs=1e-9)
    flat = blend([(0.5, a), (0.5, b)], "cartesian")
    assert math.hypot(*flat) == pytest.approx(math.radians(3.0) * math.cos(math.radians(10)))


def test_a_cell_with_ok_cells_on_one_side_only_holds_the_nearest():
    cells = [cell(1.0, 1000.0, th=(0.01, 0.02)), cell(2.0, 1000.0, th=(0.05, 0.0)), cell(3.0, 1000.0, "failed", None)]
    f = fill_cells(cells, {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0], "udc_v": [12.0]})[(3.0, 1000.0, 12.0)]
    assert (f.theta_cos, f.theta_sin) == (0.05, 0.0) and f.source.startswith("held")


def test_a_cell_with_no_ok_cell_on_its_lines_is_left_a_hole():
    cells = [
        cell(1.0, 1000.0, th=(0.01, 0.0)),
        cell(2.0, 1500.0, "failed", None),
        cell(1.0, 1500.0, "failed", None),
        cell(2.0, 1000.0, "failed", None),
    ]
    fills = fill_cells(cells, {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1500.0], "udc_v": [12.0]})
    assert (2.0, 1500.0, 12.0) not in fills  # its lines: 1 Nm at 1500 and 1000 rpm at 2 Nm, both failed
    assert (1.0, 1500.0, 12.0) in fills and (2.0, 1000.0, 12.0) in fills


def row(t, n, status, th=(0.0, 0.0), sweep_pass=None, s=None) -> dict:
    details = {} if sweep_pass is None else {"sweep_pass": sweep_pass}
    if s is not None:
        details["s_matrix"] = s
    return {
        "torque_nm": t,
        "speed_rpm": n,
        "udc_v": 12.0,
        "status": status,
        "theta_cos": th[0],
        "theta_sin": th[1],
        "detail": {"details": details},
    }


def test_second_pass_takes_each_non_ok_point_once_in_plan_order():
    plan = SweepPlan.from_grid(Grid(torque_nm=[1, 2], speed_rpm=[1000, 2000], udc_v=[12]))
    current = [
        row(1, 1000, "ok"),
        row(2, 1000, "below_target", sweep_pass=1),
        row(2, 2000, "failed"),
        row(1, 2000, "below_target", sweep_pass=2),
    ]
    again = second_pass_points(plan, current)
    # plan order: 1 Nm (1000, 2000 rpm), then 2 Nm reversed (2000, 1000 rpm); 1 Nm / 2000 rpm already had its
    # second pass
    assert [(op.torque_nm, op.speed_rpm) for op in again] == [(2.0, 2000.0), (2.0, 1000.0)]


def test_the_second_pass_prior_lies_between_the_neighbours_on_both_sides():
    s = [[1.0, 0.2], [-0.2, 1.0]]
    a, b = theta(3.0, 280.0), theta(5.0, 300.0)
    rows = [row(1.0, 1500.0, "ok", a, s=s), row(3.0, 1500.0, "ok", b), row(2.0, 1500.0, "below_target", (0.5, 0.5))]
    prior = prior_from_neighbours(OperatingPoint(torque_nm=2.0, speed_rpm=1500, udc_v=12), rows, AXES)
    # what the drive would inject midway in its plane (drivers/lut_image.DEFAULT_INTERPOLATION)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(blend([(0.5, a), (0.5, b)], DEFAULT_INTERPOLATION))
    if DEFAULT_INTERPOLATION == "polar":
        assert (prior.theta_cos, prior.theta_sin) == pytest.approx(theta(4.0, 290.0))
    assert prior.s_matrix is not None and "between 1 and 3" in prior.source


def test_a_second_pass_starts_from_its_own_first_attempt_where_that_beat_the_harmonic_clearly():
    """Between neighbours across the field-weakening turn an interpolated prior may be far off; a first
    attempt that reached 41 dB (below target only by its confirmation margin) is the better start."""
    s = [[1.0, 0.2], [-0.2, 1.0]]
    own = theta(2.37, 250.6)
    first = {**row(2.0, 1500.0, "below_target", own), "suppression_db": MEASURED_MIN_DB + 21.1}
    rows = [row(1.0, 1500.0, "ok", theta(3.0, 280.0), s=s), row(3.0, 1500.0, "ok", theta(5.0, 300.0)), first]
    prior = prior_from_neighbours(OperatingPoint(torque_nm=2.0, speed_rpm=1500, udc_v=12), rows, AXES)
    assert (prior.theta_cos, prior.theta_sin) == pytest.approx(own)
    assert prior.source.startswith("its own earlier attempt (below_target, 41.1 dB)") and "S from 1 Nm" in prior.source
    # one that did not beat the harmonic clearly is no better than the neighbours
    first["suppression_db"] = MEASURED_MIN_DB - 1
    prior = prior_from_neighbours(OperatingPoint(torque_nm=2.0, speed_rpm=1500, udc_v=12), rows, AXES)
    assert "between 1 and 3" in prior.source
