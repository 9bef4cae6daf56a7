"""Plans that know the regime: the predicted field-weakening onset (closed form, eq. 18-20) against an
independent computation and a hand-worked number, the speeds a plan places around it, the preview's
plan and estimate, and that the engine queues the same plan the preview shows."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from service.model.operating_point import (
    OperatingPoint,
    field_weakening_onset,
    field_weakening_onset_rpm,
    nominal_steady_state,
)
from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.runs.identify import parse_options
from service.runs.plans import (
    ESTIMATE_MEASUREMENT_S,
    ESTIMATE_RUN_START_S,
    ESTIMATE_SETTLE_S_PER_POINT,
    Grid,
    RegimeError,
    RegimePlacement,
    SweepPlan,
    plan_grid,
    preview_sweep,
)
from service.settings import MotorSettings, SettingsError, load_settings
from service.store.storage import Storage

PAPER = MotorSettings()  # paper-bench nominal: N_p 4, R_s 10 mOhm, L_d = L_q 20 uH, psi_p 7 mWb, I_max 113 A
SETTINGS = load_settings(environ={})
EXAMPLE = Grid(torque_nm=[1, 2, 3, 4], speed_rpm=[1000, 1400, 1800, 2200, 2600], udc_v=[12])
AROUND = RegimePlacement(speeds_around_onset=True, spacing_rpm=100)


def _bisected_onset_rpm(torque_nm: float, udc_v: float, margin: float) -> float:
    """Independent of the closed form: the speed at which nominal_steady_state (bisection on i_d, its own
    voltage equations) starts field weakening. It weakens above U_dc/sqrt(3), so it is asked at
    margin * U_dc; the onset is found by bisection on speed over its `field_weakening` flag."""

    def weakening(speed_rpm: float) -> bool:
        op = OperatingPoint(torque_nm=torque_nm, speed_rpm=speed_rpm, udc_v=margin * udc_v)
        return nominal_steady_state(op, PAPER).field_weakening

    lo, hi = 1e-3, 30_000.0
    assert not weakening(lo) and weakening(hi)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if weakening(mid) else (mid, hi)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("udc_v", [8.0, 12.0, 24.0])
@pytest.mark.parametrize("margin", [0.8, 0.95, 1.0])
@pytest.mark.parametrize("torque_nm", [0.0, 0.5, 2.5, 4.0, 4.7])
def test_onset_closed_form_matches_bisection_on_the_nominal_steady_state(torque_nm, margin, udc_v):
    onset = field_weakening_onset(torque_nm, udc_v, PAPER, margin)
    assert onset.speed_rpm == pytest.approx(_bisected_onset_rpm(torque_nm, udc_v, margin), abs=1e-6)
    # at the onset |u_dq| with i_d = 0 sits exactly on margin * U_dc / sqrt(3)
    op = OperatingPoint(torque_nm=torque_nm, speed_rpm=onset.speed_rpm, udc_v=udc_v)
    at = nominal_steady_state(op, PAPER)
    # (at margin 1 rounding may put it a hair above the limit: i_d then a few 1e-14 A)
    assert abs(at.i_d_a) < 1e-9 and at.u_magnitude_v == pytest.approx(margin * udc_v / math.sqrt(3), rel=1e-12)
    assert onset.omega_e_rad_s == pytest.approx(at.omega_e_rad_s, rel=1e-12)


def test_onset_hand_worked_for_paper_bench_at_12_v():
    """k_T = 1.5 * 4 * 7 mWb = 0.042 Nm/A; U = 0.95 * 12 V / sqrt(3) = 6.5818 V.
    2.5 Nm: i_q = 59.524 A; a = (20e-6 * 59.524)^2 + 0.007^2 = 5.0417e-5 V^2 s^2, b = 2 * 0.01 * 59.524 * 0.007
    = 8.3333e-3 V^2 s, c = (0.01 * 59.524)^2 - 6.5818^2 = -42.966 V^2; omega_e = (-b + sqrt(b^2 - 4ac)) / 2a
    = 844.2 rad/s -> 844.2 / 4 * 60 / (2 pi) = 2015.4 rpm.
    4 Nm: i_q = 95.238 A; a = 5.2628e-5, b = 1.3333e-2, c = -42.413 -> omega_e = 779.9 rad/s -> 1862.0 rpm.
    (Without the margin, at U_dc/sqrt(3) = 6.928 V, they would be 2131.9 and 1976.0 rpm.)"""
    at_25 = field_weakening_onset(2.5, 12.0, PAPER, 0.95)
    assert at_25.i_q_a == pytest.approx(59.524, abs=1e-3) and at_25.u_limit_v == pytest.approx(6.5818, abs=1e-4)
    assert at_25.omega_e_rad_s == pytest.approx(844.2, abs=0.1)
    assert at_25.speed_rpm == pytest.approx(2015.4, abs=0.1)
    assert field_weakening_onset_rpm(4.0, 12.0, PAPER, 0.95) == pytest.approx(1862.0, abs=0.1)
    assert field_weakening_onset_rpm(2.5, 12.0, PAPER, 1.0) == pytest.approx(2131.9, abs=0.1)
    assert field_weakening_onset_rpm(4.0, 12.0, PAPER, 1.0) == pytest.approx(1976.0, abs=0.1)


def test_onset_falls_with_torque_rises_with_udc_and_ignores_the_torque_sign():
    torques = [0.0, 1.0, 2.0, 3.0, 4.0, 4.5]
    at_12 = [field_weakening_onset_rpm(t, 12.0, PAPER, 0.95) for t in torques]
    assert at_12 == sorted(at_12, reverse=True)
    # no load: |u| = omega_e psi_p, so omega_e = U / psi_p exactly
    assert at_12[0] == pytest.approx(0.95 * 12 / math.sqrt(3) / 7e-3 / 4 * 60 / (2 * math.pi), rel=1e-12)
    assert field_weakening_onset_rpm(2.5, 24.0, PAPER, 0.95) > 1.9 * at_12[3]
    # the firmware computes its references from |T*|: braking weakens the field at the same speed
    assert field_weakening_onset_rpm(-2.5, 12.0, PAPER, 0.95) == field_weakening_onset_rpm(2.5, 12.0, PAPER, 0.95)


def test_no_onset_where_the_torque_is_not_reached_or_beyond_the_speeds_of_interest():
    beyond_current = field_weakening_onset(5.0, 12.0, PAPER, 0.95)  # 119 A > I_max 113 A
    assert beyond_current.speed_rpm is None and "i_max_a" in beyond_current.reason
    at_standstill = field_weakening_onset(4.0, 1.5, PAPER, 0.95)  # R_s i_q = 0.95 V > U = 0.82 V
    assert at_standstill.speed_rpm is None and "standstill" in at_standstill.reason
    assert field_weakening_onset(1.0, 0.0, PAPER, 0.95).speed_rpm is None
    assert field_weakening_onset(1.0, 1e300, PAPER, 0.95).speed_rpm is None  # no finite onset, no exception
    assert field_weakening_onset_rpm(2.5, 48.0, PAPER, 0.95) == pytest.approx(8654.3, abs=0.1)
    assert field_weakening_onset_rpm(2.5, 48.0, PAPER, 0.95, max_speed_rpm=6000) is None


def test_voltage_margin_is_a_bounded_nominal_control_setting():
    assert SETTINGS.control.voltage_margin == 0.95
    assert load_settings(environ={"RIPPLECAL_CONTROL__VOLTAGE_MARGIN": "0.9"}).control.voltage_margin == 0.9
    assert load_settings(environ={}, overrides={"control.voltage_margin": 1.0}).control.voltage_margin == 1.0
    for bad in (0.5, 1.01, 0.0):
        with pytest.raises(SettingsError, match="control.voltage_margin"):
            load_settings(environ={}, overrides={"control.voltage_margin": bad})


# --- the plan ------------------------------------------------------------------------------------------
def test_plan_places_speeds_at_and_around_each_onset_within_the_grid():
    planned = plan_grid(EXAMPLE, AROUND, SETTINGS)
    # onsets 2158.7, 2064.6, 1965.0, 1862.0 rpm -> 2160, 2060, 1960, 1860 and +-100 rpm
    assert planned.added_speeds_rpm == [1760.0, 1860.0, 1960.0, 2060.0, 2160.0, 2260.0]
    assert planned.grid.speed_rpm == [
        1000.0,
        1400.0,
        1760.0,
        1800.0,
        1860.0,
        1960.0,
        2060.0,
        2160.0,
        2200.0,
        2260.0,
        2600.0,
    ]
    assert planned.grid.torque_nm == EXAMPLE.torque_nm and planned.grid.udc_v == EXAMPLE.udc_v
    by_torque = {o.torque_nm: o for o in planned.onsets}
    for t, o in by_torque.items():
        assert o.onset_rpm == pytest.approx(field_weakening_onset_rpm(t, 12.0, PAPER, 0.95), abs=0.05)
        assert o.in_speed_range and o.placed_rpm == 10 * round(o.onset_rpm / 10)
        # cells on both sides of the turn
        assert {o.placed_rpm - 100, o.placed_rpm, o.placed_rpm + 100} <= set(planned.grid.speed_rpm)
    [v2160] = [v for v in planned.speed_axis if v.speed_rpm == 2160.0]
    assert v2160.added and any("onset of 1 Nm at 12 V" in r for r in v2160.reasons)
    assert not any(v.added for v in planned.speed_axis if v.speed_rpm in EXAMPLE.speed_rpm)


def test_without_placement_the_grid_stays_and_the_onsets_are_still_predicted():
    for regime in (None, RegimePlacement(), RegimePlacement(speeds_around_onset=False, spacing_rpm=300)):
        planned = plan_grid(EXAMPLE, regime, SETTINGS)
        assert planned.grid == EXAMPLE and planned.added_speeds_rpm == []
        assert [o.onset_rpm for o in planned.onsets] == [2158.7, 2064.6, 1965.0, 1862.0]
        assert all(o.placed_rpm is None for o in planned.onsets)


def test_placement_stays_inside_the_grids_speed_range():
    # 2 Nm: onset 2064.6 -> 2060 and 1960 inside 1000..2100, 2160 not; 1 Nm (2158.7): outside, nothing placed
    planned = plan_grid(Grid(torque_nm=[1, 2], speed_rpm=[1000, 2100]), AROUND, SETTINGS)
    assert planned.added_speeds_rpm == [1960.0, 2060.0]
    one = planned.onsets[0]
    assert not one.in_speed_range and one.placed_rpm is None and "outside the grid's speeds" in one.note
    # a single speed: no range to place into
    assert plan_grid(Grid(torque_nm=[2.5], speed_rpm=[2000]), AROUND, SETTINGS).added_speeds_rpm == []
    # no onset below safety.max_speed_rpm: said so, nothing placed; a torque beyond I_max: said why
    fast = plan_grid(Grid(torque_nm=[2.5, 5], speed_rpm=[1000, 6000], udc_v=[48]), AROUND, SETTINGS)
    assert [o.onset_rpm for o in fast.onsets] == [None, None] and fast.added_speeds_rpm == []
    assert "safety.max_speed_rpm" in fast.onsets[0].note and "i_max_a" in fast.onsets[1].note


def test_onsets_per_udc_and_the_round_and_spacing_options():
    planned = plan_grid(
        Grid(torque_nm=[2.5], speed_rpm=[1000, 5000], udc_v=[12, 24]),
        RegimePlacement(speeds_around_onset=True, spacing_rpm=250, round_rpm=50),
        SETTINGS,
    )
    at_12, at_24 = planned.onsets
    assert (at_12.udc_v, at_24.udc_v) == (12.0, 24.0)
    assert at_12.placed_rpm == 2000.0 and at_24.placed_rpm == 50 * round(at_24.onset_rpm / 50)
    assert planned.added_speeds_rpm == sorted(
        [1750.0, 2000.0, 2250.0, at_24.placed_rpm - 250, at_24.placed_rpm, at_24.placed_rpm + 250]
    )


def test_regime_fields_are_bounded_and_closed():
    for bad in (
        {"spacing_rpm": 5},
        {"spacing_rpm": 5000},
        {"round_rpm": 0},
        {"spacing_rpm": math.nan},
        {"speeds_around_onset": True, "extra": 1},
    ):
        with pytest.raises(ValidationError):
            RegimePlacement.model_validate(bad)


def test_too_many_speed_values_after_placement_is_a_regime_error():
    grid = Grid(torque_nm=[1, 2, 3, 4], speed_rpm=[1000 + 7 * k for k in range(199)])  # 1000..2386 rpm
    with pytest.raises(RegimeError, match="more than the grid's 200"):
        plan_grid(grid, AROUND, SETTINGS)


# --- the preview and the engine ------------------------------------------------------------------------
def test_preview_points_are_the_plan_of_the_planned_grid_and_the_estimate_is_its_arithmetic():
    # 4 Nm at 2600 rpm is beyond what the motor settings hold at 12 V: the envelope model overridden here
    options = parse_options("adaptive", {"override_envelope_model": True})
    p = preview_sweep(EXAMPLE, AROUND, "adaptive", options, False, SETTINGS)
    assert p.accepted and p.problems == []
    assert tuple(p.points) == SweepPlan.from_grid(plan_grid(EXAMPLE, AROUND, SETTINGS).grid).points
    assert p.total == len(p.points) == 4 * 11
    est = p.estimate
    per_point = ESTIMATE_SETTLE_S_PER_POINT + ESTIMATE_MEASUREMENT_S["adaptive"]
    assert est.estimated_s == pytest.approx(ESTIMATE_RUN_START_S + 44 * per_point, abs=0.05)
    h_hz = [op.speed_rpm / 60 * 4 * 6 for op in p.points]
    worst = ESTIMATE_RUN_START_S + 44 * ESTIMATE_SETTLE_S_PER_POINT + sum(options.plant_time_bound_s(f) for f in h_hz)
    assert est.worst_case_s == pytest.approx(worst, abs=0.05) and est.udc_changes == 0
    assert "estimate" in est.basis and "speedup 1" in est.basis
    # a method without a typical figure counts its worst case
    grid_method = preview_sweep(EXAMPLE, None, "grid", parse_options("grid", {}), False, SETTINGS).estimate
    assert grid_method.estimated_s == grid_method.worst_case_s


def test_preview_lists_every_problem_post_sweeps_would_refuse():
    p = preview_sweep(
        Grid(torque_nm=[1, 9], speed_rpm=[50, 2000]), None, "adaptive", parse_options("adaptive", {}), False, SETTINGS
    )
    assert not p.accepted
    assert {tuple(e["loc"]) for e in p.problems} == {("body", "grid", "torque_nm"), ("body", "grid", "speed_rpm")}
    assert all(e["type"] == "value_error.bench_limits" for e in p.problems)
    # 400 points requested: the placed speeds make it larger than safety.max_sweep_points_unconfirmed
    big = Grid(torque_nm=[1 + 0.1 * k for k in range(20)], speed_rpm=[1000 + 80 * k for k in range(20)])
    p = preview_sweep(big, AROUND, "probe", parse_options("probe", {}), False, SETTINGS)
    assert [e["loc"] for e in p.problems] == [["body", "confirm_large"]] and p.total > 400
    assert preview_sweep(big, AROUND, "probe", parse_options("probe", {}), True, SETTINGS).accepted
    # a grid no operating point can take: named, no points, no estimate, no exception
    p = preview_sweep(Grid(torque_nm=[1], speed_rpm=[0]), AROUND, "probe", parse_options("probe", {}), False, SETTINGS)
    assert p.points == [] and p.estimate is None and p.problems[0]["loc"] == ["body", "grid", "speed_rpm"]
    assert "speed_rpm 0 is below the minimum of" in p.problems[0]["msg"], p.problems


class _Bench:
    identity = "unit:no-bench"

    def check_reachable(self) -> None:  # a bench that was reached at start
        pass


def test_engine_submit_sweep_stores_the_grid_and_plan_the_preview_shows(tmp_path):
    storage = Storage(str(tmp_path / "plans.db"))
    engine = Engine(storage, _Bench(), SETTINGS, EventBroker())  # never started: the sweep stays queued
    options = parse_options("probe", {"override_envelope_model": True})  # 4 Nm at 2600 rpm: beyond the model
    sweep_id = engine.submit_sweep(EXAMPLE, "probe", options, regime=AROUND)
    sweep = storage.get_sweep(sweep_id)
    preview = preview_sweep(EXAMPLE, AROUND, "probe", options, False, SETTINGS)
    assert Grid.model_validate(sweep["grid"]) == preview.grid
    assert sweep["total_points"] == preview.total
    # the run rebuilds its plan from the stored grid: the same points in the same order
    assert SweepPlan.from_grid(Grid.model_validate(sweep["grid"])).points == tuple(preview.points)
    # without a regime the grid is stored as requested
    plain = storage.get_sweep(engine.submit_sweep(EXAMPLE, "probe", options))
    assert Grid.model_validate(plain["grid"]) == EXAMPLE
