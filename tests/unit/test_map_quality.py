"""Map quality (service/maps/quality.py) on closed-form maps: a map linear in the operating point has
no outlier, one planted outlier is flagged alone with the numbers its reason gives, non-ok cells are
never references, and the smoothed view replaces only the outlier (the stored map stays as measured)."""

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from service.api.public.maps import map_public
from service.maps import quality as map_quality
from service.maps.lut_export import export_map
from tests.support.maps import make_map, theta_of

# non-uniform speed axis: the expected step scales with the grid spacing
GRID = {"torque_nm": [1.0, 2.0, 3.0, 4.0], "speed_rpm": [1000.0, 1500.0, 2500.0, 3000.0], "udc_v": [12.0]}
THETA0 = np.array(theta_of(3.0, 280.0))
G_T = np.array([0.004, -0.002])  # rad per Nm
G_N = np.array([-1.0e-5, 1.5e-5])  # rad per rpm


def linear(p):
    t = THETA0 + G_T * (p[0] - 2.5) + G_N * (p[1] - 2000.0)
    return float(t[0]), float(t[1])


def planted(at, offset):
    def theta(p):
        tc, ts = linear(p)
        return (tc + offset[0], ts + offset[1]) if p == at else (tc, ts)

    return theta


OFFSET = np.array(theta_of(1.5, 40.0))  # 1.5 deg, in some direction


# `storage` (tests/conftest.py): every test here runs on SQLite and on PostgreSQL


def _cell(m, t, n, u=12.0):
    return next(c for c in m["cells"] if (c["torque_nm"], c["speed_rpm"], c["udc_v"]) == (t, n, u))


def test_linear_map_has_no_outlier_and_its_gradients_are_the_slopes(storage):
    m = map_public(storage, make_map(storage, GRID, linear)).model_dump()
    assert {c["quality"] for c in m["cells"]} == {"consistent"}
    q = m["quality"]
    assert (q["outliers"], q["unchecked"], q["consistent"]) == (0, 0, 16)
    assert q["gradient_deg_per_unit"]["torque_nm"] == pytest.approx(math.degrees(np.hypot(*G_T)), rel=1e-9)
    assert q["gradient_deg_per_unit"]["speed_rpm"] == pytest.approx(math.degrees(np.hypot(*G_N)), rel=1e-9)
    assert q["gradient_deg_per_unit"]["udc_v"] is None  # one voltage: no pair on that axis


def test_planted_interior_outlier_is_flagged_alone_with_closed_form_numbers(storage):
    at = (2.0, 1500.0, 12.0)
    m = map_public(storage, make_map(storage, GRID, planted(at, OFFSET))).model_dump()
    flagged = [c for c in m["cells"] if c["quality"] == "outlier"]
    assert [(c["torque_nm"], c["speed_rpm"]) for c in flagged] == [(2.0, 1500.0)]
    assert m["quality"]["outliers"] == 1
    # independently: the median of the 4 neighbours of an interior cell of a linear map is the
    # linear value, so the deviation is the planted offset; the expected step is the median of the
    # neighbour distances times the slopes (torque 1 Nm both sides, speed 500 and 1000 rpm)
    deviation_deg = math.degrees(np.hypot(*OFFSET))
    steps = sorted([np.hypot(*G_T) * 1.0, np.hypot(*G_T) * 1.0, np.hypot(*G_N) * 500.0, np.hypot(*G_N) * 1000.0])
    expected_deg = math.degrees((steps[1] + steps[2]) / 2)
    reason = flagged[0]["outlier_reason"]
    assert f"theta {deviation_deg:.2f} deg from the median of its 4 ok neighbours" in reason
    assert f"{deviation_deg / expected_deg:.1f}x the step expected to them ({expected_deg:.2f} deg" in reason
    assert "measure this point again" in reason


def test_planted_corner_outlier_does_not_spoil_its_neighbours(storage):
    at = (1.0, 1000.0, 12.0)
    m = map_public(storage, make_map(storage, GRID, planted(at, 2 * OFFSET))).model_dump()
    assert [(c["torque_nm"], c["speed_rpm"]) for c in m["cells"] if c["quality"] == "outlier"] == [(1.0, 1000.0)]
    assert "of its 2 ok neighbours" in _cell(m, 1.0, 1000.0)["outlier_reason"]


def test_a_step_within_the_factor_is_not_an_outlier(storage):
    # half the expected step off: well inside 3x (no threshold within a hair)
    small = OFFSET / np.hypot(*OFFSET) * 0.5 * np.hypot(*G_T)
    m = map_public(storage, make_map(storage, GRID, planted((2.0, 1500.0, 12.0), small))).model_dump()
    assert m["quality"]["outliers"] == 0


def test_non_ok_cells_are_never_references():
    axes = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 2000.0, 3000.0], "udc_v": [12.0]}
    cells = []
    for n in axes["speed_rpm"]:
        for t in axes["torque_nm"]:
            tc, ts = linear((t, n, 12.0))
            cells.append(
                {"torque_nm": t, "speed_rpm": n, "udc_v": 12.0, "status": "ok", "theta_cos": tc, "theta_sin": ts}
            )
    # a below_target cell with a wild theta next to the centre: not a reference, not judged
    cells[1].update(status="below_target", theta_cos=1.0, theta_sin=-1.0)
    q = map_quality.assess(cells, axes)
    assert (1.0, 2000.0, 12.0) not in [k for k, c in q.cells.items() if c.quality == "outlier"]
    assert (2.0, 1000.0, 12.0) not in q.cells
    assert q.count("outlier") == 0
    assert (2.0, 1000.0, 12.0) not in q.cells[(2.0, 2000.0, 12.0)].neighbours
    # a line whose middle failed: each end has no ok neighbour left to compare with
    line = [c for c in cells if c["speed_rpm"] == 1000.0]
    q = map_quality.assess(line, {**axes, "speed_rpm": [1000.0]})
    assert {c.quality for c in q.cells.values()} == {"unchecked"}


def test_smoothed_view_replaces_only_the_outlier_and_leaves_the_stored_map(storage):
    at = (3.0, 2500.0, 12.0)
    map_id = make_map(storage, GRID, planted(at, OFFSET))
    measured = map_public(storage, map_id).model_dump()
    smooth = map_public(storage, map_id, smooth=True).model_dump()
    assert smooth["smoothed"] and smooth["quality"]["smoothed"] == 1 and smooth["quality"]["outliers"] == 0
    cell = _cell(smooth, 3.0, 2500.0)
    assert cell["quality"] == "smoothed" and cell["status"] == "ok"
    # the neighbours' median is the linear value here (interior cell of a linear map)
    assert (cell["theta_cos"], cell["theta_sin"]) == pytest.approx(linear(at), abs=1e-12)
    assert cell["suppression_db"] is None  # nothing was measured at this theta
    assert f"result {cell['result_id']}" in cell["smoothed_from"] and "3.0x" not in cell["smoothed_from"]
    assert cell["outlier_reason"] == _cell(measured, 3.0, 2500.0)["outlier_reason"]
    others = [(c["theta_cos"], c["suppression_db"]) for c in smooth["cells"] if c is not cell]
    assert others == [
        (c["theta_cos"], c["suppression_db"])
        for c in measured["cells"]
        if (c["torque_nm"], c["speed_rpm"]) != (3.0, 2500.0)
    ]
    # the stored map is still the measured one
    again = map_public(storage, map_id).model_dump()
    assert _cell(again, 3.0, 2500.0)["theta_cos"] == pytest.approx(linear(at)[0] + OFFSET[0], abs=1e-12)
    assert _cell(again, 3.0, 2500.0)["quality"] == "outlier"


def test_exports_keep_their_columns_and_keys_and_carry_quality_in_comments(storage):
    map_id = make_map(storage, GRID, planted((2.0, 1500.0, 12.0), OFFSET))
    m = map_public(storage, map_id).model_dump()
    text = export_map(m, "csv")
    comments = [line for line in text.splitlines() if line.startswith("#")]
    assert any("quality: 1 outlier(s) (2 Nm / 1500 rpm / 12 V)" in line for line in comments)
    rows = list(csv.reader(io.StringIO("\n".join(line for line in text.splitlines() if not line.startswith("#")))))
    # the columns before: as they were; filled and fill_source appended (issue "The LUT holds where the motor
    # runs"), then injection_off (issue 27)
    assert rows[0] == [
        "torque_nm",
        "speed_rpm",
        "udc_v",
        "theta_cos_rad",
        "theta_sin_rad",
        "gamma_deg",
        "delta_deg",
        "suppression_db",
        "status",
        "filled",
        "fill_source",
        "injection_off",
    ]
    doc = json.loads(export_map(m, "json"))
    assert set(doc["cells"][0]) == {
        "torque_nm",
        "speed_rpm",
        "udc_v",
        "status",
        "result_id",
        "gamma_deg",
        "delta_deg",
        "theta_cos",
        "theta_sin",
        "suppression_db",
        "target_db",
        "noise_floor_db",
        "error",
        "filled",
        "fill_source",
        "injection_off",
    }
    assert doc["format_version"] == 4 and doc["quality"]["outliers"] == 1 and not doc["quality"]["smoothed_view"]
    assert doc["quality"]["cells"][0]["outlier_reason"].startswith("theta ")
    assert "quality: 1 outlier(s)" in export_map(m, "c") and "quality: 1 outlier(s)" in export_map(m, "dcm")
    # the smoothed export: same columns, one row changed, said in the header
    smooth = export_map(map_public(storage, map_id, smooth=True).model_dump(), "csv")
    assert "SMOOTHED view: 1 outlier cell(s)" in smooth
    plain_rows = [line for line in text.splitlines() if not line.startswith("#")]
    smooth_rows = [line for line in smooth.splitlines() if not line.startswith("#")]
    assert len(plain_rows) == len(smooth_rows)
    changed = [a for a, b in zip(plain_rows, smooth_rows) if a != b]
    assert len(changed) == 1 and changed[0].startswith("2.0,1500.0,12.0,")


def test_past_the_one_by_one_share_every_cell_over_the_factor_is_flagged(storage, monkeypatch):
    """After ONE_BY_ONE_SHARE of the cells the rest over the factor are flagged at once (a read stays
    fast on a noisy map): no cell called consistent is then further than the factor from its fit."""
    monkeypatch.setattr(map_quality, "ONE_BY_ONE_SHARE", 0.0)  # one by one for the first only
    planted_at = {(1.0, 1000.0, 12.0), (4.0, 1500.0, 12.0), (2.0, 3000.0, 12.0)}  # no two share a neighbour

    def theta(p):
        tc, ts = linear(p)
        return (tc + 2 * OFFSET[0], ts + 2 * OFFSET[1]) if p in planted_at else (tc, ts)

    m = map_public(storage, make_map(storage, GRID, theta)).model_dump()
    assert {(c["torque_nm"], c["speed_rpm"], c["udc_v"]) for c in m["cells"] if c["quality"] == "outlier"} == planted_at
    q = map_quality.assess(m["cells"], m["axes"])
    assert all(c.score <= map_quality.OUTLIER_FACTOR for c in q.cells.values() if c.quality == "consistent")


def test_every_outlier_of_a_noisy_map_keeps_the_reason_it_was_flagged_for():
    """A third of the cells spoiled at random, some cells not ok: an outlier whose neighbours are
    flagged after it has no fit left; it keeps the one that flagged it (such a map once gave a 500)."""
    import random

    rnd = random.Random(23)
    cells = []
    for t in GRID["torque_nm"]:
        for n in GRID["speed_rpm"]:
            spoiled = rnd.random() < 0.35
            cells.append(
                {
                    "torque_nm": t,
                    "speed_rpm": n,
                    "udc_v": 12.0,
                    "status": "ok" if rnd.random() < 0.9 else "failed",
                    "theta_cos": 0.05 + 0.001 * t + (rnd.gauss(0, 0.02) if spoiled else 0.0),
                    "theta_sin": 0.02 - 1e-5 * n + (rnd.gauss(0, 0.02) if spoiled else 0.0),
                }
            )
    q = map_quality.assess(cells, GRID)
    outliers = [c for c in q.cells.values() if c.quality == "outlier"]
    assert outliers and all(c.fit is not None and "deg from the median" in c.reason for c in outliers)


# a refined map: speed breakpoints inserted where the map bends (non-uniform spacing)
REFINED = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 1500.0, 1800.0, 2000.0, 2600.0], "udc_v": [12.0]}


def _cells(axes, theta, status=None):
    status = status or {}
    return [
        {
            "torque_nm": t,
            "speed_rpm": n,
            "udc_v": u,
            "status": status.get((t, n, u), "ok"),
            "theta_cos": theta((t, n, u))[0],
            "theta_sin": theta((t, n, u))[1],
        }
        for u in axes["udc_v"]
        for n in axes["speed_rpm"]
        for t in axes["torque_nm"]
    ]


def test_refined_map_fit_interpolates_by_position():
    """(2 Nm, 1800 rpm) sits 300 rpm above 1500 and 200 below 2000: the fit of a linear map is its
    linear value there (the plain median of the four neighbours would lean to 1500 rpm); a planted
    offset is flagged with exactly its size, and the smoothed view gives back the linear value."""
    at = (2.0, 1800.0, 12.0)
    q = map_quality.assess(_cells(REFINED, linear), REFINED)
    assert q.count("outlier") == 0 and q.count("consistent") == 15
    assert q.cells[at].fit == pytest.approx(linear(at), abs=1e-15)
    assert q.cells[at].deviation_rad == pytest.approx(0.0, abs=1e-15)
    assert q.gradient_rad_per_unit["speed_rpm"] == pytest.approx(np.hypot(*G_N), rel=1e-9)

    spoiled = _cells(REFINED, planted(at, 3 * OFFSET))
    q = map_quality.assess(spoiled, REFINED)
    assert [k for k, c in q.cells.items() if c.quality == "outlier"] == [at]
    c = q.cells[at]
    assert c.deviation_rad == pytest.approx(np.hypot(*(3 * OFFSET)), rel=1e-9)
    # expected step: median of the steps to the 4 neighbours (1 Nm twice, 300 rpm, 200 rpm)
    steps = sorted([np.hypot(*G_T), np.hypot(*G_T), np.hypot(*G_N) * 300.0, np.hypot(*G_N) * 200.0])
    assert c.expected_step_rad == pytest.approx((steps[1] + steps[2]) / 2, rel=1e-9)
    smoothed = map_quality.smoothing(q, 1, {})
    assert smoothed[at][0] == pytest.approx(linear(at), abs=1e-15)


def test_refined_map_through_storage_has_no_outlier(storage):
    m = map_public(storage, make_map(storage, REFINED, linear)).model_dump()
    assert m["axes"]["speed_rpm"] == REFINED["speed_rpm"]
    assert (m["quality"]["outliers"], m["quality"]["unchecked"], m["quality"]["consistent"]) == (0, 0, 15)


def test_filled_cells_are_neither_judged_nor_references():
    """A filled cell carries a fill, not a measurement: with a wild theta it is no outlier and no
    neighbour of anyone; its ok neighbours are judged as if it had no theta."""
    at = (2.0, 1800.0, 12.0)
    cells = _cells(REFINED, linear, {at: "below_target"})
    for c in cells:
        if (c["torque_nm"], c["speed_rpm"], c["udc_v"]) == at:
            c.update(filled=True, fill_source="measured", theta_cos=1.0, theta_sin=-1.0)
    q = map_quality.assess(cells, REFINED)
    assert at not in q.cells and q.count("outlier") == 0
    assert all(at not in c.neighbours for c in q.cells.values())
    # (2 Nm, 1500 rpm) lost its neighbour above: 3 left (1 and 3 Nm, 1000 rpm)
    assert len(q.cells[(2.0, 1500.0, 12.0)].neighbours) == 3


# a refined map: a slow map with a fast turn between 2150 and 2250 rpm resolved by breakpoints every 25 rpm
TURN_GRID = {
    "torque_nm": [1.0, 2.0, 3.0, 4.0],
    "speed_rpm": [1000.0, 1400.0, 1800.0, 2150.0, 2175.0, 2200.0, 2225.0, 2250.0, 2600.0],
    "udc_v": [12.0],
}


def turning(p):
    """theta* turning by 120 deg around 2200 rpm (a smooth tanh step of the phase, 25 rpm wide) at 3 deg, the slow
    linear map elsewhere: the change across a turn cell is 30-50x the map's median per-rpm change."""
    tc, ts = linear(p)
    phase = math.radians(60.0) * (1.0 + math.tanh((p[1] - 2200.0) / 25.0))
    g = math.hypot(tc, ts)
    return g * math.cos(math.atan2(ts, tc) + phase), g * math.sin(math.atan2(ts, tc) + phase)


def test_a_turn_resolved_by_close_breakpoints_is_not_an_outlier_and_a_bad_cell_on_it_still_is(storage):
    m = map_public(storage, make_map(storage, TURN_GRID, turning)).model_dump()
    assert m["quality"]["outliers"] == 0, [c["outlier_reason"] for c in m["cells"] if c["quality"] == "outlier"]
    at = (2.0, 1400.0, 12.0)  # away from the turn: its neighbours agree, so 1.5 deg is still 3x what they expect

    def spoiled(p):
        tc, ts = turning(p)
        return (tc + OFFSET[0], ts + OFFSET[1]) if p == at else (tc, ts)

    m = map_public(storage, make_map(storage, TURN_GRID, spoiled)).model_dump()
    assert [(c["torque_nm"], c["speed_rpm"]) for c in m["cells"] if c["quality"] == "outlier"] == [at[:2]]


REFINED_TURN_MAP = Path(__file__).resolve().parents[1] / "data" / "refined_turn_map.json"


def test_a_refined_maps_turn_is_not_called_outliers_and_a_bad_cell_on_it_still_is():
    """paper-bench's refined map (tests/data/refined_turn_map.json): at its low-torque edge rows theta* changes
    fast with torque and loops at the turn, so a cell with one torque neighbour is fitted along the line to the
    next row beyond it (not to that neighbour's value alone): no outlier. A cell 3 deg off (about 2x |theta| of
    the low rows' 1.5..4 deg) is flagged alone, at the edge row, at the turn and inside."""
    data = json.loads(REFINED_TURN_MAP.read_text())
    keys = ("torque_nm", "speed_rpm", "udc_v", "status", "theta_cos", "theta_sin")
    cells = [dict(zip(keys, row, strict=True)) for row in data["cells"]]
    assert map_quality.assess(cells, data["axes"]).count("outlier") == 0
    for at in [(1.0, 2250.0), (1.0, 1400.0), (1.5, 2450.0), (2.0, 1400.0), (4.0, 1000.0)]:
        spoiled = [
            {**c, "theta_cos": c["theta_cos"] + OFFSET[0] * 2.0, "theta_sin": c["theta_sin"] + OFFSET[1] * 2.0}
            if (c["torque_nm"], c["speed_rpm"]) == at
            else c
            for c in cells
        ]
        q = map_quality.assess(spoiled, data["axes"])
        assert [k[:2] for k, c in q.cells.items() if c.quality == "outlier"] == [at], at


# a refined map past the turn: flat to 2000 rpm, then theta* moves 0.01 deg per rpm (1 deg per 100 rpm), the last
# speed 100 rpm beyond a pair 50 rpm apart
TURN_AXES = {
    "torque_nm": [1.0, 2.0, 3.0],
    "speed_rpm": [1000.0, 1200.0, 1400.0, 1600.0, 1800.0, 2000.0, 2100.0, 2150.0, 2250.0],
    "udc_v": [12.0],
}
FAST_RAD_PER_RPM = np.array([math.radians(0.01), 0.0])


def past_the_turn(p):
    t = np.array(theta_of(3.0, 280.0)) + FAST_RAD_PER_RPM * max(0.0, p[1] - 2000.0)
    return float(t[0]), float(t[1])


def test_an_axis_end_past_the_turn_moves_as_fast_as_the_pair_before_it():
    # the last cell's one speed neighbour (2150) is 100 rpm away and the one beyond it (2100) 50 rpm: the line is not
    # extrapolated over twice its span, but the map's change there (1 deg per 100 rpm, the median change along speed
    # is 0) is the step expected, so the end is not an outlier of a map that turns fast
    q = map_quality.assess(_cells(TURN_AXES, past_the_turn), TURN_AXES)
    assert all(c.quality == "consistent" for c in q.cells.values()), {
        k: c.reason for k, c in q.cells.items() if c.quality != "consistent"
    }


def test_a_below_target_cells_own_theta_is_a_reference_not_judged():
    # theta* loops at 2200 rpm (a fifth of a turn each 25 rpm at 1 Nm, slower with torque): the cell at 2200 rpm has
    # speed neighbours on both sides only where 2225's below-target measurement counts as one
    axes = {"torque_nm": [1.0, 1.25, 1.5], "speed_rpm": [2100.0, 2150.0, 2200.0, 2225.0, 2250.0], "udc_v": [12.0]}

    def loop(p):
        phase = math.radians(72.0 / 25.0 * (p[1] - 2100.0) / p[0])
        g = math.radians(1.0)
        return g * math.cos(phase), g * math.sin(phase)

    at = (1.0, 2225.0, 12.0)

    def filled(source):
        cells = _cells(axes, loop, {at: "below_target"})
        for c in cells:
            if (c["torque_nm"], c["speed_rpm"], c["udc_v"]) == at:
                c.update(filled=True, fill_source=source)  # the fill of its own theta: theta as measured
        return cells

    q = map_quality.assess(filled("measured: its own theta (below_target, 43.8 dB against the uncompensated)"), axes)
    assert at not in q.cells  # a reference, not judged
    assert q.cells[(1.0, 2200.0, 12.0)].quality == "consistent"
    assert at in q.cells[(1.0, 2200.0, 12.0)].neighbours
    # a fill made from the neighbours is no measurement: not a reference
    q = map_quality.assess(filled("interpolated (polar) from ok cells"), axes)
    assert at not in q.cells[(1.0, 2200.0, 12.0)].neighbours
