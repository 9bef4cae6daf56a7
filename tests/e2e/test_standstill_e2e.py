"""A run ends with the shaft at standstill, not coasting from the load's speed-loop overshoot.

A load braking on its PI speed loop swings through zero (service/bench/standstill.py). make_safe judged
standstill from one 20 ms DAQ block below 20 rpm, so it could disable the load at the zero crossing: the shaft
then coasted at the overshoot's speed (-40 rpm seen), and a shutdown's own make_safe waited on it past the
forced exit (CI: `ripplecal serve` ended unorderly on two signals, heartbeat consumers left armed). A load with
a slow speed loop (3 Hz: the crossing lasts long enough that a block lands in it) makes that the rule, not the
exception. At --speedup 1: the plant keeps turning after the run, as a real shaft does."""

from __future__ import annotations

import time

import pytest

from plant_emulator import scenario as scn
from tests.support.bench_rig import served_bench

pytestmark = pytest.mark.e2e

SLOW_LOAD_LOOP_HZ = 3.0


def _slow_load_scenario(directory):
    text = open(scn.resolve("paper-bench")).read()
    assert "speed_bandwidth_hz = 8.0" in text  # the line replaced below (else this test proves nothing)
    path = directory / "slow-load.toml"
    path.write_text(text.replace("speed_bandwidth_hz = 8.0", f"speed_bandwidth_hz = {SLOW_LOAD_LOOP_HZ}"))
    return path


def _shaft(emu) -> tuple[float, str]:
    faults = emu.control({"status": True})["faults"]
    return faults["drive_speed_rpm"], faults["load_state"]


def test_runs_end_with_the_shaft_at_standstill_whether_finished_or_cancelled(tmp_path):
    args = ("--scenario", str(_slow_load_scenario(tmp_path)))
    with served_bench(tmp_path, "s.db", speedup=1.0, emulator_args=args) as (emu, _svc, api, _db):
        for speed_rpm, cancel in ((1500, False), (1000, True), (2000, False)):
            r = api.post(
                "/identifications", {"operating_point": {"torque_nm": 1.5, "speed_rpm": speed_rpm}, "method": "probe"}
            )
            assert r.status_code == 202, r.text
            job_id = r.json()["id"]
            if cancel:  # the watchdog's stop: torque off, the load left braking for the run's make_safe
                api.wait(lambda: abs(_shaft(emu)[0]) > 0.9 * speed_rpm, 60, "the shaft at speed")
                assert api.post(f"/jobs/{job_id}/cancel").status_code == 200
            job = api.job_finished(job_id, 120)
            assert job["state"] == ("cancelled" if cancel else "done"), job
            # the run is over: the load disabled, and the shaft stays still (a coasting one would not)
            readings = []
            for _ in range(10):
                readings.append(_shaft(emu))
                time.sleep(0.1)
            assert all(state == "switch_on_disabled" for _, state in readings), readings
            assert max(abs(rpm) for rpm, _ in readings) < 20.0, (speed_rpm, cancel, readings)
