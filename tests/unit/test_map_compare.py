"""Map comparison (service/maps/compare.py) against closed forms: two maps whose thetas differ by a
known vector, on a bench with a known measured S, residual and uncompensated phasor; the predicted
suppression is computed here independently, in the complex form of docs/conventions.md, Secondary path (A = a_c - j a_s,
Theta = theta_cos - j theta_sin, A = S (Theta_d + Theta))."""

import math

import pytest

from service.api.public.maps import map_public
from service.maps.compare import compare_maps, wrap_deg
from tests.support.maps import RESIDUAL, S_MEASURED, UNCOMPENSATED, make_map, theta_of

GRID = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]}
DELTA = theta_of(0.8, 150.0)  # theta_b - theta_a, rad


def base(p):
    return theta_of(2.0 + 0.3 * p[0], 270.0 + p[1] / 100.0)


def shifted(p):
    tc, ts = base(p)
    return tc + DELTA[0], ts + DELTA[1]


# `storage` (tests/conftest.py): every test here runs on SQLite and on PostgreSQL


def _gamma_delta_deg(tc, ts):
    return math.degrees(math.hypot(tc, ts)), math.degrees(-math.atan2(ts, tc)) % 360.0


def test_known_shift_and_known_s_give_the_closed_form_deltas_and_prediction(storage):
    a, b = make_map(storage, GRID, base), make_map(storage, GRID, shifted)
    cmp = compare_maps(storage, a, b).model_dump()
    assert cmp["same_axes"] and cmp["summary"]["compared"] == 6 and cmp["summary"]["without_s"] == 0
    residual = complex(RESIDUAL[0], -RESIDUAL[1])
    uncompensated = abs(complex(*UNCOMPENSATED))
    predicted_db = 20 * math.log10(uncompensated / abs(residual + S_MEASURED * complex(DELTA[0], -DELTA[1])))
    for c in cmp["cells"]:
        p = (c["torque_nm"], c["speed_rpm"], c["udc_v"])
        ga, da = _gamma_delta_deg(*base(p))
        gb, db = _gamma_delta_deg(*shifted(p))
        assert c["compared"] and c["note"] is None
        assert c["delta_gamma_deg"] == pytest.approx(gb - ga, abs=1e-9)
        wrapped = (db - da + 180.0) % 360.0 - 180.0
        assert c["delta_delta_deg"] == pytest.approx(wrapped, abs=1e-9)
        assert c["delta_theta_deg"] == pytest.approx(math.degrees(math.hypot(*DELTA)), rel=1e-12)
        assert c["predicted_suppression_db"] == pytest.approx(predicted_db, abs=1e-9)
    s = cmp["summary"]
    assert s["median_delta_theta_deg"] == pytest.approx(0.8, rel=1e-12) == pytest.approx(s["max_delta_theta_deg"])
    assert s["min_predicted_suppression_db"] == pytest.approx(predicted_db, abs=1e-9)
    # a shift that large costs most of the measured suppression
    measured_db = 20 * math.log10(uncompensated / abs(residual))
    assert predicted_db < measured_db - 20


def test_worst_cell_is_the_one_that_moved_most(storage):
    far = (4.0, 2000.0, 12.0)

    def moved(p):
        tc, ts = base(p)
        k = 3.0 if p == far else 1.0
        return tc + k * DELTA[0], ts + k * DELTA[1]

    cmp = compare_maps(storage, make_map(storage, GRID, base), make_map(storage, GRID, moved)).model_dump()
    worst = cmp["summary"]["worst_cell"]
    assert (worst["torque_nm"], worst["speed_rpm"], worst["udc_v"]) == far
    assert cmp["summary"]["max_delta_theta_deg"] == pytest.approx(2.4, rel=1e-12)
    assert cmp["summary"]["median_delta_theta_deg"] == pytest.approx(0.8, rel=1e-12)
    assert cmp["summary"]["worst_predicted_cell"] == cmp["summary"]["worst_cell"]


def test_delta_is_wrapped_across_360():
    assert wrap_deg(1.0 - 359.0) == pytest.approx(2.0)
    assert wrap_deg(359.0 - 1.0) == pytest.approx(-2.0)
    assert wrap_deg(180.0) == 180.0 and wrap_deg(-180.0) == 180.0 and wrap_deg(0.0) == 0.0


def test_cells_across_the_wrap_compare_by_the_short_way(storage):
    a = make_map(storage, GRID, lambda p: theta_of(3.0, 359.0))
    b = make_map(storage, GRID, lambda p: theta_of(3.0, 1.0))
    cell = compare_maps(storage, a, b).cells[0]
    assert cell.delta_delta_deg == pytest.approx(2.0, abs=1e-9)
    assert cell.delta_theta_deg == pytest.approx(2 * 3.0 * math.sin(math.radians(1.0)), rel=1e-9)


def test_a_map_against_itself_has_zero_deltas_and_its_measured_suppression(storage):
    a = make_map(storage, GRID, base)
    cmp = compare_maps(storage, a, a)
    measured = map_public(storage, a).cells[0].suppression_db
    assert all(c.delta_theta_deg == 0.0 and c.delta_gamma_deg == 0.0 and c.delta_delta_deg == 0.0 for c in cmp.cells)
    assert cmp.summary.median_predicted_suppression_db == pytest.approx(measured, abs=1e-9)


def test_different_axes_compare_on_the_intersection_and_list_the_rest(storage):
    a = make_map(storage, GRID, base)
    b = make_map(storage, {**GRID, "torque_nm": [2.5, 4.0, 5.5]}, shifted)
    cmp = compare_maps(storage, a, b)
    assert not cmp.same_axes
    assert {(c.torque_nm, c.speed_rpm) for c in cmp.cells} == {
        (2.5, 1000.0),
        (4.0, 1000.0),
        (2.5, 2000.0),
        (4.0, 2000.0),
    }
    assert {(p.torque_nm, p.speed_rpm) for p in cmp.only_in_a} == {(1.0, 1000.0), (1.0, 2000.0)}
    assert {(p.torque_nm, p.speed_rpm) for p in cmp.only_in_b} == {(5.5, 1000.0), (5.5, 2000.0)}
    assert (cmp.summary.only_in_a, cmp.summary.only_in_b, cmp.summary.compared) == (2, 2, 4)


def test_not_ok_cells_and_missing_s_are_said_per_cell(storage):
    a = make_map(storage, GRID, base, status={(1.0, 1000.0, 12.0): "failed"}, s_measured=None)
    b = make_map(storage, GRID, shifted, status={(2.5, 1000.0, 12.0): "below_target"})
    cmp = compare_maps(storage, a, b)
    by = {(c.torque_nm, c.speed_rpm): c for c in cmp.cells}
    assert not by[(1.0, 1000.0)].compared and "map a has failed" in by[(1.0, 1000.0)].note
    assert not by[(2.5, 1000.0)].compared and "map b has below_target" in by[(2.5, 1000.0)].note
    ok = by[(4.0, 1000.0)]
    assert ok.compared and ok.predicted_suppression_db is None and "stored no measured S" in ok.note
    assert ok.delta_theta_deg == pytest.approx(0.8, rel=1e-12)
    assert (cmp.summary.compared, cmp.summary.not_compared, cmp.summary.without_s) == (4, 2, 4)
    assert cmp.summary.median_predicted_suppression_db is None


def test_a_refined_map_against_the_coarse_one_compares_on_the_shared_points(storage):
    """A refinement inserts speed breakpoints (1500, 1800 rpm) between the coarse ones: the shared
    points are compared with the closed-form deltas, the inserted ones are listed as only in b."""
    coarse = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0, 2600.0], "udc_v": [12.0]}
    refined = {**coarse, "speed_rpm": [1000.0, 1500.0, 1800.0, 2000.0, 2600.0]}
    cmp = compare_maps(storage, make_map(storage, coarse, base), make_map(storage, refined, shifted))
    assert not cmp.same_axes and cmp.summary.compared == 9 and cmp.summary.not_compared == 0
    assert {(c.torque_nm, c.speed_rpm) for c in cmp.cells} == {
        (t, n) for t in coarse["torque_nm"] for n in coarse["speed_rpm"]
    }
    assert {(p.torque_nm, p.speed_rpm) for p in cmp.only_in_b} == {
        (t, n) for t in coarse["torque_nm"] for n in (1500.0, 1800.0)
    }
    assert cmp.only_in_a == [] and cmp.summary.only_in_b == 6
    for c in cmp.cells:
        p = (c.torque_nm, c.speed_rpm, c.udc_v)
        ga, da = _gamma_delta_deg(*base(p))
        gb, db = _gamma_delta_deg(*shifted(p))
        assert c.delta_gamma_deg == pytest.approx(gb - ga, abs=1e-9)
        assert c.delta_delta_deg == pytest.approx((db - da + 180.0) % 360.0 - 180.0, abs=1e-9)
        assert c.delta_theta_deg == pytest.approx(0.8, rel=1e-12)


def test_a_filled_cell_is_not_compared_and_said_filled(storage):
    """A filled cell carries a fill, not a measurement (service/maps/fill.py): not compared, its note
    names the fill and its source; the other cells compare as before."""
    from service.maps.compare import compare_views

    a_id, b_id = make_map(storage, GRID, base), make_map(storage, GRID, shifted)
    a, b = map_public(storage, a_id), map_public(storage, b_id)
    source = "interpolated (cartesian) from ok cells: torque_nm between 1 and 4"
    b.cells[1] = b.cells[1].model_copy(update={"status": "below_target", "filled": True, "fill_source": source})
    results = storage.results_by_id([c.result_id for c in a.cells if c.result_id is not None])
    cmp = compare_views(a, b, results)
    cell = next(c for c in cmp.cells if (c.torque_nm, c.speed_rpm) == (b.cells[1].torque_nm, b.cells[1].speed_rpm))
    assert not cell.compared and cell.delta_theta_deg is None
    assert f"map b has below_target (filled: {source})" in cell.note and "a fill is not compared" in cell.note
    assert (cmp.summary.compared, cmp.summary.not_compared) == (5, 1)
