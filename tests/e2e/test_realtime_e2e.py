"""The bench's clock: `ripplecal serve --emulate --speedup 1`, the emulator streaming as a real DAQ does.

A small sweep and its validation run as continuous bench runs in real time. Assertions are on states
and on what real time means (a run cannot take less wall time than the plant time it measured), never
on how fast it went: the figures are `make bench`'s (tests/benchmarks/bench_realtime.py)."""

from __future__ import annotations

import time

import pytest

from tests.support.bench_rig import Api
from tests.support.service_process import ServiceProcess
from tests.support.sweep_checks import holes

pytestmark = pytest.mark.e2e
GRID = {"torque_nm": [2.0, 3.0], "speed_rpm": [1500, 2000], "udc_v": [12]}
SPLIT = {"move_s", "accounting_s", "settle_s", "measurement_s"}


def test_a_sweep_and_its_validation_in_real_time(tmp_path):
    db = tmp_path / "rt.db"
    svc = ServiceProcess(db, "--emulate", "--speedup", "1")
    try:
        svc.wait_ready()
        api = Api(svc, db)
        started = time.monotonic()
        r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
        assert r.status_code == 202, r.text
        sweep = api.sweep_finished(r.json()["id"], 300)
        sweep_wall_s = time.monotonic() - started
        assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
        points = [p["result"] for p in sweep["points"]]
        assert len(points) == 4 and sum(p["status"] == "ok" for p in points) >= 3, points
        for p in points:
            # every point's wall time split (move, accounting, settle, measurement), the plant time on the DAQ clock
            assert SPLIT <= set(p["details"]["bench_time_s"]), p["details"]
            assert p["plant_time_s"] > 0 and p["details"]["op_settle_plant_s"] > 0
        plant_s = sum(p["plant_time_s"] + p["details"]["op_settle_plant_s"] for p in points)
        assert sweep_wall_s >= plant_s, (sweep_wall_s, plant_s)  # real time: no faster than the plant

        m = api.get(f"/maps/{sweep['map_id']}")
        started = time.monotonic()
        r = api.post(f"/maps/{m['id']}/validate", {"force": holes(m) > 0})
        assert r.status_code == 202, r.text
        job = api.job_finished(r.json()["id"], 300)
        validation_wall_s = time.monotonic() - started
        assert job["state"] == "done", job
        cells = job["validation"]["cells"]
        assert len(cells) == 9 and all(c["status"] == "measured" for c in cells), cells
        # every point's settling on the DAQ clock, counted in the validation's bench time
        assert all(c["settle_plant_s"] > 0 for c in cells), cells
        bench_s = sum(c["plant_time_s"] + c["settle_plant_s"] for c in cells)
        assert job["validation"]["plant_time_s"] == pytest.approx(bench_s)
        assert validation_wall_s >= bench_s  # real time: no faster than the plant

        # run-ups in the same run, each analysed (a survey of 48 orders over a 12.5 s ramp: seconds) before the next
        # point moves: the DAQ goes on being read meanwhile, so every pair is judged (unread, it overflowed and the
        # next setpoints' sync toggles were miscounted: "more sync toggles seen than setpoints written")
        options = {"runups": True, "runup_torques_max": 2, "runup_rate_rpm_per_s": 40}
        r = api.post(f"/maps/{m['id']}/validate", {"force": holes(m) > 0, "options": options})
        assert r.status_code == 202, r.text
        job = api.job_finished(r.json()["id"], 600)
        assert job["state"] == "done", job
        v = job["validation"]
        runup_cells = [c for c in v["cells"] if c["kind"] == "runup"]
        assert runup_cells and all(c["status"] == "measured" for c in runup_cells), [
            c["error"] for c in runup_cells if c["status"] != "measured"
        ]
        assert v["torques_run_up"] == [2.0, 3.0], v["torques_run_up"]
        assert v["runup_plant_time_s"] >= 4 * 500 / 40  # two pairs of 12.5 s ramps
        status = api.get("/bench/status")
        assert not status["busy"] and status["drive"]["state"] == "switch_on_disabled", status
        api.close()
    finally:
        svc.stop()
