"""What a refinement round adds (service/runs/refinement.py plan_round), on hand-made maps and validations."""

from __future__ import annotations

import math

from service.maps.lut_export import injection_unchanged, injects_nothing
from service.maps.placement import axes_with
from service.model.operating_point import OperatingPoint
from service.runs.refinement import (
    failing_points,
    guard_cells,
    harmful_points,
    no_progress,
    plan_round,
    reuse_where,
)
from service.runs.runup_validation import is_harm, mark_no_injection
from service.runs.validation import ValidationItem

AXES = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 2000.0, 3000.0], "udc_v": [12.0]}


def map_cells(theta=lambda t, n: (0.01 * t, 0.0)) -> list[dict]:
    out = []
    for n in AXES["speed_rpm"]:
        for t in AXES["torque_nm"]:
            c, s = theta(t, n)
            out.append({"torque_nm": t, "speed_rpm": n, "udc_v": 12.0, "status": "ok", "theta_cos": c, "theta_sin": s})
    return out


def vcell(t, n, db, kind=None, status="measured") -> dict:
    grid = t in AXES["torque_nm"] and n in AXES["speed_rpm"]
    return {
        "operating_point": {"torque_nm": t, "speed_rpm": n, "udc_v": 12.0},
        "kind": kind or ("grid" if grid else "midpoint"),
        "status": status,
        "suppression_db": db if status == "measured" else None,
    }


def validation(overrides: dict) -> list[dict]:
    """Every point of the finer grid at 45 dB, but those in `overrides` {(t, n): dB or None (failed)}."""
    cells = []
    for n in (1000.0, 1500.0, 2000.0, 2500.0, 3000.0):
        for t in (1.0, 1.5, 2.0, 2.5, 3.0):
            db = overrides.get((t, n), 45.0)
            cells.append(vcell(t, n, db, status="measured" if db is not None else "failed"))
    return cells


def test_nothing_to_do_when_every_point_holds():
    plan = plan_round(AXES, map_cells(), validation({}), 30.0, 100)
    assert plan.failing == 0 and plan.cells == [] and plan.inserted == {}


def test_failing_points_are_those_below_target_or_not_measured():
    cells = validation({(1.5, 1000.0): 29.9, (2.5, 3000.0): None})
    assert {
        (c["operating_point"]["torque_nm"], c["operating_point"]["speed_rpm"]) for c in failing_points(cells, 30.0)
    } == {(1.5, 1000.0), (2.5, 3000.0)}


def test_a_failing_speed_midpoint_inserts_its_speed_a_row_of_cells():
    # the whole 2500 rpm row of midpoints fails: theta turns between 2000 and 3000 rpm
    plan = plan_round(
        AXES,
        map_cells(lambda t, n: (0.01 * t, 0.02 if n == 3000.0 else 0.0)),
        validation({(t, 2500.0): 12.0 for t in (1.0, 1.5, 2.0, 2.5, 3.0)}),
        30.0,
        100,
    )
    assert plan.inserted == {"speed_rpm": [2500.0]}
    assert sorted(plan.new_cells) == [(1.0, 2500.0, 12.0), (2.0, 2500.0, 12.0), (3.0, 2500.0, 12.0)]
    assert plan.remeasure == []


def test_a_diagonal_midpoint_inserts_on_the_axis_where_theta_steps_most():
    # theta changes with speed only: a point midway in torque and speed inserts the speed value
    plan = plan_round(
        AXES, map_cells(lambda t, n: (0.01 + 0.01 * (n == 3000.0), 0.0)), validation({(2.5, 2500.0): 15.0}), 30.0, 100
    )
    assert plan.inserted == {"speed_rpm": [2500.0]}


def test_a_grid_point_that_misses_at_its_own_cell_is_identified_again():
    plan = plan_round(AXES, map_cells(), validation({(2.0, 2000.0): 25.0}), 30.0, 100)
    assert plan.remeasure == [(2.0, 2000.0, 12.0)] and plan.inserted == {} and plan.new_cells == []


def test_the_budget_decides_what_fits_and_says_what_did_not():
    row = {(t, 2500.0): 12.0 for t in (1.0, 1.5, 2.0, 2.5, 3.0)}  # inserting 2500 rpm costs 3 cells
    plan = plan_round(AXES, map_cells(lambda t, n: (0.01, 0.02 * (n == 3000.0))), validation(row), 30.0, 2)
    assert plan.inserted == {} and plan.new_cells == []
    assert any("needs 3 cells, 2 left" in r for r in plan.reasons)
    # the verdict a person reads: one clause, the values grouped per axis (issue 30: no run-on)
    assert plan.why_nothing_fits(None) == "inserting speed_rpm 2500 needs more cells than the 2 left"


def test_points_served_per_cell_come_first_and_weak_candidates_wait():
    # five failing points want 2500 rpm (3 cells: 5/3 per cell); one grid point wants a re-measure (1/1);
    # one torque midpoint wants 1.5 Nm (3 cells: 1/3 per cell, below a quarter of the best: next round)
    fails = {(t, 2500.0): 12.0 for t in (1.0, 1.5, 2.0, 2.5, 3.0)}
    fails.update({(1.0, 1000.0): 20.0, (1.5, 2000.0): 29.0})
    plan = plan_round(AXES, map_cells(lambda t, n: (0.01 * t, 0.02 * (n == 3000.0))), validation(fails), 30.0, 100)
    assert plan.inserted == {"speed_rpm": [2500.0]}
    assert plan.remeasure == [(1.0, 1000.0, 12.0)]
    assert "torque_nm" not in plan.inserted


def test_values_inserted_on_two_axes_add_their_crossing_once():
    fails = {(t, 2500.0): 10.0 for t in (1.0, 1.5, 2.0, 2.5, 3.0)}
    fails.update({(2.5, n): 10.0 for n in (1000.0, 1500.0, 2000.0, 2500.0, 3000.0)})
    cells = map_cells(lambda t, n: (0.01 + 0.02 * (t == 3.0), 0.02 * (n == 3000.0)))
    plan = plan_round(AXES, cells, validation(fails), 30.0, 100)
    assert plan.inserted == {"speed_rpm": [2500.0], "torque_nm": [2.5]}
    # 3 cells of the new row, 3 of the new column, 1 at their crossing
    assert len(plan.new_cells) == 7 and (2.5, 2500.0, 12.0) in plan.new_cells
    new_axes = axes_with(AXES, plan.inserted)
    assert new_axes["speed_rpm"] == [1000.0, 2000.0, 2500.0, 3000.0] and new_axes["torque_nm"] == [1.0, 2.0, 2.5, 3.0]
    assert math.prod(len(v) for v in new_axes.values()) == 9 + len(plan.new_cells)


def runup_bin(t, n, db, holds=None, above_floor_db=40.0) -> dict:
    return {
        **vcell(t, n, db, kind="runup"),
        "holds": db >= 30.0 if holds is None else holds,
        "above_floor_db": above_floor_db,
    }


def test_a_stretch_of_failing_runup_bins_is_one_claim_at_its_worst_bin():
    # 1.0 Nm row: bins 1400..1460 fail (worst at 1430); 2.5 Nm midpoint: one bin at 2600 fails
    cells = validation({})
    cells += [runup_bin(1.0, float(n), 45.0) for n in range(1000, 1400, 10)]
    cells += [runup_bin(1.0, float(n), 10.0 if n != 1430 else 2.0) for n in range(1400, 1470, 10)]
    cells += [runup_bin(2.5, 2600.0, 20.0)]
    plan = plan_round(AXES, map_cells(lambda t, n: (0.01 * t, 0.0005 * n)), cells, 30.0, 100)
    assert plan.failing == 8
    # one value for the stretch of 7 (serving 7 points for 3 cells), not seven; the single bin (1 point for 3
    # cells) waits for the next validation (ROUND_SCORE_FRACTION)
    assert plan.inserted == {"speed_rpm": [1430.0]}


def test_a_runup_bin_holding_by_the_floor_rule_is_not_failing():
    held_by_floor = runup_bin(1.0, 1500.0, 12.0, holds=True)
    assert failing_points([held_by_floor], 30.0) == []
    assert failing_points([runup_bin(1.0, 1500.0, 12.0)], 30.0) != []


def test_max_bytes_refuses_an_insertion_that_would_not_fit_the_firmware_memory():
    # image bytes = 24 header and CRC + 4 per breakpoint + 9 per cell: 3 x 3 x 1 -> 24 + 28 + 81 = 133 bytes;
    # a speed inserted -> 3 x 4 x 1: 24 + 32 + 108 = 164 bytes
    cells = validation({(2.0, 1500.0): 10.0})
    assert plan_round(AXES, map_cells(lambda t, n: (0.0, 0.0001 * n)), cells, 30.0, 100, max_bytes=164).inserted
    plan = plan_round(AXES, map_cells(lambda t, n: (0.0, 0.0001 * n)), cells, 30.0, 100, max_bytes=163)
    assert not plan.inserted and "164 bytes, over max_bytes = 163" in plan.reasons[0]
    assert plan.why_nothing_fits(163) == "inserting speed_rpm 1500 makes the LUT larger than max_bytes = 163"


def test_the_verdict_lists_a_few_values_per_axis_and_counts_the_rest():
    from service.runs.refinement import RoundPlan

    plan = RoundPlan(over_cells={"speed_rpm": [2470.0, 2290.0, 2410.0, 2350.0], "torque_nm": [2.9]}, cells_left=3)
    assert plan.why_nothing_fits(None) == (
        "inserting speed_rpm 2290, 2350, 2410 (and 1 more) and torque_nm 2.9 needs more cells than the 3 left"
    )
    assert RoundPlan().why_nothing_fits(None) == "nothing left to insert"


def test_image_bytes_is_the_size_of_the_image_the_drive_takes():
    from service.maps.lut_export import image_bytes, lut_image

    cells = [{**c, "udc_v": 12.0, "filled": False, "result_id": None} for c in map_cells()]
    m = {"id": 1, "harmonic_order": 6, "axes": AXES, "cells": cells}
    assert image_bytes(AXES) == len(lut_image(m)) == 133


def test_harm_turns_injection_off_at_the_corner_nearest_the_turn():
    # theta* small at (2 Nm, 2000 rpm): a bin worse than nothing between 1.5..2 Nm x 2000..3000 rpm
    def theta(t, n):
        return (0.0001, 0.0) if (t, n) == (2.0, 2000.0) else (0.02, 0.01)

    harmful = [runup_bin(1.5, 2400.0, -4.0, above_floor_db=45.0), runup_bin(1.5, 2410.0, -1.0, above_floor_db=10.0)]
    assert harmful_points(harmful) == harmful[:1]  # under 20 dB above the floor it is not harm
    assert guard_cells(AXES, map_cells(theta), harmful_points(harmful)) == [(2.0, 2000.0, 12.0)]
    # a point on a grid line has only that line's corners
    on_line = [runup_bin(2.0, 2400.0, -3.0)]
    assert guard_cells(AXES, map_cells(theta), on_line) == [(2.0, 2000.0, 12.0)]


def lut_map(axes, theta, off=(), map_id=1, lut_cells="float32") -> dict:
    """A map as the LUT exports read it: every cell ok at theta(t, n), injection off at `off`."""
    cells = [
        {
            "torque_nm": t,
            "speed_rpm": n,
            "udc_v": 12.0,
            "status": "ok",
            "theta_cos": theta(t, n)[0],
            "theta_sin": theta(t, n)[1],
            "filled": False,
            "injection_off": (t, n) in off,
        }
        for n in axes["speed_rpm"]
        for t in axes["torque_nm"]
    ]
    return {"id": map_id, "harmonic_order": 6, "axes": axes, "cells": cells, "provenance": {"lut_cells": lut_cells}}


def smooth(t, n):
    return (0.01 * t + 1e-5 * n, 0.02 - 0.003 * t)


def point(t, n):
    return {"torque_nm": t, "speed_rpm": n, "udc_v": 12.0}


def test_the_drives_injection_is_unchanged_only_where_no_changed_cell_weighs():
    """Injection off at (2 Nm, 2000 rpm): the drive's theta changes wherever that cell is a corner of non-zero weight
    (1 < t < 3 Nm and 1000 < n < 3000 rpm, on its own lines only there) and along the run-ups at such torques. A
    speed value inserted at 2500 rpm with a theta off the line: only in 2000..3000 rpm, and along every run-up."""
    for cells in ("float32", "int11"):
        before = lut_map(AXES, smooth, lut_cells=cells)
        same = injection_unchanged(before, lut_map(AXES, smooth, off=[(2.0, 2000.0)], lut_cells=cells))
        touched = {(t, n) for t in (1.5, 2.0, 2.5) for n in (1500.0, 2000.0, 2500.0)}
        for t in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0):
            for n in (900.0, 1000.0, 1500.0, 2000.0, 2500.0, 3000.0):
                assert same(point(t, n), False) is ((t, n) not in touched), (cells, t, n)
        assert not same(point(1.5, 1000.0), True) and same(point(1.0, 1000.0), True) and same(point(3.0, 0.0), True)
        axes = {**AXES, "speed_rpm": [1000.0, 2000.0, 2500.0, 3000.0]}
        same = injection_unchanged(
            before, lut_map(axes, lambda t, n: (0.05, 0.0) if n == 2500.0 else smooth(t, n), lut_cells=cells)
        )
        assert same(point(1.5, 1500.0), False) and same(point(2.0, 2000.0), False)
        assert not same(point(1.5, 2250.0), False) and not same(point(3.0, 2750.0), False)
        assert not same(point(1.0, 1000.0), True)


def test_the_drive_injects_nothing_only_where_an_off_cell_weighs_over_the_whole_bin():
    """Injection off at (2 Nm, 2000 rpm): by the drive's rule (drivers/lut_image.py, any corner of weight > 0 at
    flag 3) nothing is injected for 1 < t < 3 Nm x 1000 < n < 3000 rpm, and on the lines through the cell within
    that; a run-up bin is nothing only when every speed it spans is."""
    for cells in ("float32", "int11"):
        nothing = injects_nothing(lut_map(AXES, smooth, off=[(2.0, 2000.0)], lut_cells=cells))
        off = {(t, n) for t in (1.5, 2.0, 2.5) for n in (1500.0, 2000.0, 2500.0)}
        for t in (1.0, 1.5, 2.0, 2.5, 3.0):
            for n in (1000.0, 1500.0, 2000.0, 2500.0, 3000.0):
                assert nothing(point(t, n), 0.0) is ((t, n) in off), (cells, t, n)
        assert nothing(point(1.5, 1995.0), 5.0) and nothing(point(1.5, 2985.0), 5.0)  # 1990..2000, 2980..2990
        assert not nothing(point(1.5, 2995.0), 5.0)  # at 3000 rpm, its end, the cell at 2000 rpm weighs 0
        assert not nothing(point(1.5, 1003.0), 5.0)  # 998..1008 reaches below 1000 rpm, where the cell weighs 0
        assert not nothing(point(1.0, 2000.0), 5.0)  # on the 1 Nm row the cell at 2 Nm weighs 0
    assert not injects_nothing(lut_map(AXES, smooth))(point(2.0, 2000.0), 5.0)


def test_where_the_drive_injects_nothing_a_figure_below_zero_is_no_harm():
    """Two measurements without injection differ by a little either way: marked no_injection (with the reason
    said), such a point is never harm, so the guard does not chase it; elsewhere the same figure is."""
    nothing = injects_nothing(lut_map(AXES, smooth, off=[(2.0, 2000.0)]))
    inside, outside = runup_bin(1.5, 2400.0, -0.8, above_floor_db=40.0), runup_bin(1.5, 1000.0, -0.8, 40.0)
    inside["bin_rpm"] = outside["bin_rpm"] = 10.0
    inside["holds"] = outside["holds"] = False
    mark_no_injection([inside, outside], nothing)
    assert inside["no_injection"] and "injects nothing" in inside["reason"] and "no_injection" not in outside
    assert harmful_points([inside, outside]) == [outside]
    assert is_harm(-0.8, 40.0) and not is_harm(-0.8, 40.0, no_injection=True)


def test_a_rounds_validation_takes_the_earlier_cells_where_the_injection_is_the_same():
    previous = [{**c, "plant_time_s": 0.4} for c in validation({})]
    previous += [{**runup_bin(t, n, 40.0), "plant_time_s": 0.0} for t in (1.0, 1.5) for n in (1000.0, 1010.0)]
    previous[0] = {**previous[0], "status": "failed"}  # (1 Nm, 1000 rpm) failed then: measured now
    changed = {(1.5, 1500.0), (1.5, 0.0)}
    reuse = reuse_where(previous, lambda op, along: (op["torque_nm"], 0.0 if along else op["speed_rpm"]) not in changed)

    def item(t, n, kind="grid"):
        return ValidationItem(OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=12.0), kind)

    assert reuse(item(1.0, 1000.0)) is None and reuse(item(1.5, 1500.0, "midpoint")) is None
    got = reuse(item(2.0, 1500.0, "midpoint"))
    assert got is not None and got[0]["reused"] and got[0]["plant_time_s"] == 0.0
    assert got[0]["operating_point"] == point(2.0, 1500.0)
    assert reuse(item(1.5, 1000.0, "runup")) is None  # its torque's injection changed
    assert [b["operating_point"]["speed_rpm"] for b in reuse(item(1.0, 1000.0, "runup"))] == [1000.0, 1010.0]
    assert reuse(item(2.5, 1000.0, "runup")) is None  # not run then
    assert reuse(ValidationItem(OperatingPoint(torque_nm=2.0, speed_rpm=1500.0, udc_v=12.0), "midpoint", "no")) is None


def test_a_refinement_ends_when_measuring_cells_again_holds_no_more_points():
    def rnd(held, inserted=None, remeasured=0):
        return {"held": held, "points_judged": 3289, "inserted": inserted or {}, "remeasured": remeasured}

    assert no_progress([rnd(3137)]) is None  # one round: nothing to compare
    assert no_progress([rnd(3137, remeasured=12), rnd(3140)]) is None  # it gained
    assert no_progress([rnd(3137, {"speed_rpm": [2212.5]}), rnd(3130)]) is None  # an insertion: judged by its plan
    assert no_progress([rnd(3137, remeasured=12), rnd(3135)]) == (
        "measuring 12 cell(s) again held no more points (3135 of 3289)"
    )
