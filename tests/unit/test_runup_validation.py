"""The judgement of a LUT along run-ups (service/runs/runup_validation.py), against closed-form figures."""

from __future__ import annotations

import math

import pytest

from service.model.limits import outside_envelope
from service.model.operating_point import OperatingPoint
from service.runs.runup_validation import judge_bins, runup_range, runup_torques
from service.settings import load_settings

SETTINGS = load_settings(environ={})


def _result(speeds, levels, floors, order=6):
    return {"speed_rpm": speeds, "orders": [order], "amplitude": [levels], "noise_floor": floors}


def test_each_bin_is_judged_by_its_ratio_the_floor_rule_and_harm():
    speeds = [1000.0, 1010.0, 1020.0, 1030.0, 1040.0]
    off = _result(speeds, [1e-2, 1e-2, 1e-2, 1e-5, 1e-2], [1e-7] * 5)
    # 40 dB, 20 dB, -6 dB (worse), a vanishing order under the floor rule, and a bin the LUT run did not fit
    lut = _result(speeds, [1e-4, 1e-3, 2e-2, 2e-5, None], [1e-7] * 5)
    cells = judge_bins(off, lut, 6, 2.0, 12.0, target_db=30.0)
    assert [c["operating_point"]["speed_rpm"] for c in cells] == speeds[:4]
    assert [round(c["suppression_db"], 6) for c in cells] == [
        40.0,
        20.0,
        round(20 * math.log10(0.5), 6),
        round(20 * math.log10(0.5), 6),
    ]
    assert [c["holds"] for c in cells] == [True, False, False, True]
    # the floor rule: 30 dB under the median uncompensated level of the range (1e-2): 3.16e-4 fs
    assert cells[3]["floor_rule_fs"] == pytest.approx(1e-2 * 10 ** (-1.5))
    assert "floor rule" in cells[3]["reason"]
    assert "worse" in cells[2]["reason"] and cells[2]["above_floor_db"] == pytest.approx(100.0)
    assert "below the target" in cells[1]["reason"]


def test_runups_run_at_every_torque_row_and_midpoint():
    assert runup_torques([3.0, 1.0, 2.0]) == [
        (1.0, "row"),
        (1.5, "midpoint"),
        (2.0, "row"),
        (2.5, "midpoint"),
        (3.0, "row"),
    ]

    # nine rows make 17 torques; at most 7 of them: evenly by index (0, 3, 5, 8, 11, 13, 16), both ends kept
    nine = runup_torques([1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 3.5, 4.0], most=7)
    assert [t for t, _ in nine] == [1.0, 1.375, 1.625, 2.0, 2.75, 3.25, 4.0]
    assert runup_torques([1.0, 2.0], most=7) == [(1.0, "row"), (1.5, "midpoint"), (2.0, "row")]


def test_a_runup_range_stops_where_the_envelope_model_stops_holding_the_torque():
    speeds = [1000.0, 1800.0, 2600.0]
    assert runup_range(1.0, 12.0, speeds, SETTINGS, False) == (1000.0, 2600.0)
    lo, hi = runup_range(4.0, 12.0, speeds, SETTINGS, False)
    assert lo == 1000.0 and hi < 2600.0
    inside = OperatingPoint(torque_nm=4.0, speed_rpm=hi, udc_v=12.0)
    beyond = OperatingPoint(torque_nm=4.0, speed_rpm=hi + 10.0, udc_v=12.0)
    assert outside_envelope(inside, SETTINGS) is None and outside_envelope(beyond, SETTINGS) is not None
    assert runup_range(4.0, 12.0, speeds, SETTINGS, True) == (1000.0, 2600.0)  # overridden
