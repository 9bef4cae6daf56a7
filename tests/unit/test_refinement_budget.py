"""A refinement's bench time budget spent ahead (service/runs/refinement.py BenchBudget): a validation's predicted
cost counted from its own items (every point of the finer grid at VALIDATION_POINT_S, each run-up pair two ramps
over the map's speed range at the validation's rate plus RUNUP_APPROACH_S each), and the placement leaving out a
value whose cells and validation would not fit (service/maps/placement.py place, `affordable`)."""

from __future__ import annotations

import pytest

from service.maps.placement import place
from service.runs.refinement import RUNUP_APPROACH_S, VALIDATION_POINT_S, BenchBudget
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
    assert affordable_candidates(budget(both_s + 0.1), AXES, candidates, measured) == candidates
    taken = affordable_candidates(budget(speed_only_s + 0.1), AXES, candidates, measured)
    assert taken == {"torque_nm": [], "speed_rpm": [1100.0]}
    assert affordable_candidates(budget(speed_only_s - 0.1), AXES, candidates, measured) == {
        "torque_nm": [],
        "speed_rpm": [],
    }
