"""A refinement's bench time budget spent ahead (service/runs/refinement.py BenchBudget): a validation's predicted
cost counted from its own items (every point of the finer grid at VALIDATION_POINT_S, each run-up pair two ramps
over the map's speed range at the validation's rate plus RUNUP_APPROACH_S each), and the placement leaving out a
value whose cells and validation would not fit (service/maps/placement.py place, `affordable`)."""

from __future__ import annotations

import math

import pytest

from service.maps.placement import axes_with, bend_db, place
from service.runs.refinement import RUNUP_APPROACH_S, VALIDATION_POINT_S, BenchBudget, point_cost_s
from service.runs.validation import ValidationOptions
from service.settings import load_settings

AXES = {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 1200.0, 1400.0], "udc_v": [12.0]}


def budget(max_bench_s: float, spent_s: float = 0.0, **options) -> BenchBudget:
    return BenchBudget(max_bench_s, spent_s, 0.5, load_settings(environ={}), ValidationOptions(**options))


def test_a_validations_cost_is_its_points_and_its_run_up_pairs():
    # the finer grid of 2 x 3 cells: 3 x 5 points, all inside the envelope at 1..2 Nm and 1000..1400 rpm
    assert budget(1e6).validation_s(AXES) == pytest.approx(15 * VALIDATION_POINT_S)
    # run-ups at the 3 torques 1, 1.5, 2 Nm: a pair each, 400 rpm at 100 rpm/s per ramp
    with_runups = budget(1e6, runups=True, runup_rate_rpm_per_s=100.0, runup_torques_max=3).validation_s(AXES)
    assert with_runups == pytest.approx(15 * VALIDATION_POINT_S + 3 * 2 * (400.0 / 100.0 + RUNUP_APPROACH_S))


def test_a_budget_says_why_cells_and_a_validation_do_not_fit():
    need_s = 4 * 0.5 + 15 * VALIDATION_POINT_S  # 4 cells at 0.5 s and the validation
    assert budget(10.0 + need_s, spent_s=10.0).against(4, AXES) is None
    why = budget(10.0 + need_s - 0.1, spent_s=10.0).against(4, AXES)
    assert why is not None and "max_bench_s" in why and "4 cell(s)" in why


def test_the_placement_leaves_out_a_value_the_budget_cannot_validate():
    judged = {"torque_nm": {1.5: [10.0]}, "speed_rpm": {1100.0: [10.0]}}  # both short of 30 + 6 dB
    kept, _following, reasons = place(AXES, judged, 30.0, None, "int11", {}, "cubic", lambda axes: None)
    assert kept == {"torque_nm": [1.5], "speed_rpm": [1100.0]} and not reasons
    # a budget that holds a grid of at most 6 cells: neither line fits
    small = lambda axes: None if len(axes["torque_nm"]) * len(axes["speed_rpm"]) <= 6 else "over the budget"  # noqa: E731
    kept, _following, reasons = place(AXES, judged, 30.0, None, "int11", {}, "cubic", small)
    assert kept == {"torque_nm": [], "speed_rpm": []}
    assert len(reasons) == 2 and all(r.endswith("left out: over the budget") for r in reasons)


def test_only_the_candidate_lines_the_budget_can_measure_and_validate_are_taken():
    from service.runs.kinds.refinement import affordable_candidates

    measured = {(t, n, 12.0) for t in AXES["torque_nm"] for n in AXES["speed_rpm"]}
    candidates = {"torque_nm": [1.5], "speed_rpm": [1100.0]}
    # the speed line: 2 cells at 0.5 s and the 3 x 7 points of the grid with it; the torque line as well: 3 more
    # cells (the crossing waits until both are kept) and 5 x 7 points
    speed_only_s = 2 * 0.5 + 21 * VALIDATION_POINT_S
    both_s = 5 * 0.5 + 35 * VALIDATION_POINT_S
    assert affordable_candidates(budget(both_s + 0.1), AXES, candidates, measured, {}) == candidates
    taken = affordable_candidates(budget(speed_only_s + 0.1), AXES, candidates, measured, {})
    assert taken == {"torque_nm": [], "speed_rpm": [1100.0]}
    assert affordable_candidates(budget(speed_only_s - 0.1), AXES, candidates, measured, {}) == {
        "torque_nm": [],
        "speed_rpm": [],
    }


SPEEDS = [1000.0, 1200.0, 1400.0, 1600.0, 1800.0]


def test_a_candidates_bend_is_the_chords_miss_of_the_curve_through_the_grid():
    # theta* quadratic along speed, q(n) = A + B n + C n^2: the Hermite with three-point slopes holds it exactly, the
    # chord between two breakpoints h apart misses it at the interval's middle by C h^2 / 4 (= q'' h^2 / 8)
    a, b, c = 0.3 + 0.4j, 1e-4 - 2e-4j, 3e-7 + 1e-7j
    axes = {"torque_nm": [1.0], "speed_rpm": SPEEDS, "udc_v": [12.0]}
    thetas = {(1.0, n, 12.0): a + b * n + c * n * n for n in SPEEDS}
    bends = bend_db(axes, {"speed_rpm": [1300.0, 1500.0]}, thetas)["speed_rpm"]
    for n in (1300.0, 1500.0):
        expected = 20 * math.log10(abs(a + b * n + c * n * n) / (abs(c) * 200.0**2 / 4))
        assert bends[n] == pytest.approx(expected, abs=1e-9)
    # straight: both interpolants agree, nothing bends; no evidence (a neighbour not identified): inf as well
    straight = {(1.0, n, 12.0): a + b * n for n in SPEEDS}
    assert bend_db(axes, {"speed_rpm": [1300.0]}, straight)["speed_rpm"][1300.0] == math.inf
    del straight[(1.0, 1400.0, 12.0)]
    assert bend_db(axes, {"speed_rpm": [1300.0]}, straight)["speed_rpm"][1300.0] == math.inf


def test_a_budget_for_one_line_takes_it_where_theta_bends_not_first_along_the_axis():
    from service.runs.kinds.refinement import affordable_candidates

    axes = {"torque_nm": [1.0, 2.0], "speed_rpm": SPEEDS, "udc_v": [12.0]}
    # theta* straight but at 1600 rpm, where it turns (both torque rows)
    thetas = {(t, n, 12.0): (0.2 + 0.5j if n == 1600.0 else 1.0 + 0.5j) for t in (1.0, 2.0) for n in SPEEDS}
    measured = set(thetas)
    candidates = {"speed_rpm": [1100.0, 1300.0, 1500.0, 1700.0]}
    one_line = axes_with(axes, {"speed_rpm": [1100.0]})
    one_line_s = 2 * 0.5 + budget(1e6).validation_s(one_line)
    taken = affordable_candidates(budget(one_line_s + 0.1), axes, candidates, measured, thetas)
    assert len(taken["speed_rpm"]) == 1 and taken["speed_rpm"][0] in (1500.0, 1700.0)  # an interval at the turn
    # with no theta* seen to bend anywhere, in order along the axis
    flat = {cell: 1.0 + 0.5j for cell in thetas}
    assert affordable_candidates(budget(one_line_s + 0.1), axes, candidates, measured, flat) == {"speed_rpm": [1100.0]}


def test_a_points_cost_is_what_the_validation_measured_itself():
    def cell(kind: str, plant_s: float, settle_s: float, **more) -> dict:
        return {"kind": kind, "status": "measured", "plant_time_s": plant_s, "settle_plant_s": settle_s, **more}

    cells = [
        cell("grid", 0.08, 0.12),
        cell("midpoint", 0.06, 0.14),
        cell("midpoint", 0.0, 0.0, reused=True),  # taken from an earlier validation: it cost nothing now
        cell("runup", 0.0, 0.0),  # a run-up's bins: the pair's cost is counted apart
        {"kind": "midpoint", "status": "failed", "error": "x"},
    ]
    assert point_cost_s(cells) == pytest.approx((0.2 + 0.2) / 2)
    assert point_cost_s([cell("runup", 0.0, 0.0)]) is None
    # the budget predicts a validation at the point cost it is given
    measured = BenchBudget(1e6, 0.0, 0.5, load_settings(environ={}), ValidationOptions(), point_s=0.25)
    assert measured.validation_s(AXES) == pytest.approx(15 * 0.25)
