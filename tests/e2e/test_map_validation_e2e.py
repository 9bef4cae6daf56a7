"""Issue 11 end to end: a map validated in the drive's own LUT mode, through the real API and emulator.

The emulator runs in its own process, the service as `ripplecal serve --bench FILE` pointed at it;
faults go through the emulator's control socket, which also tells what the drive holds in force
(injection mode, torque setpoint). A 2 x 2 sweep keeps the plant time small; assertions are on
states, reasons, counts and thresholds far from what the code reaches (grid points reach ~40-55 dB)."""

from __future__ import annotations

import math

import pytest

from tests.support.bench_rig import served_bench
from tests.support.sweep_checks import holes

pytestmark = pytest.mark.e2e
GRID = {"torque_nm": [2.0, 3.0], "speed_rpm": [1200, 1600], "udc_v": [12]}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with served_bench(tmp_path_factory.mktemp("validation"), "v.db") as (emu, _, api, _):
        yield emu, api


@pytest.fixture(scope="module")
def map_id(rig):
    _, api = rig
    r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
    assert r.status_code == 202, r.text
    sweep_id = r.json()["id"]
    sweep = api.sweep_finished(sweep_id, 240)
    assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
    return sweep["map_id"]


def drive_is_safe(emu) -> dict:
    faults = emu.control({"status": True})["faults"]
    assert faults["drive_injection_mode"] == 0 and faults["drive_torque_nm"] == 0.0, faults
    return faults


def test_validation_measures_grid_points_and_midpoints_in_lut_mode(rig, map_id):
    emu, api = rig
    m = api.get(f"/maps/{map_id}")
    force = holes(m) > 0
    r = api.post(f"/maps/{map_id}/validate", {"force": force})
    assert r.status_code == 202, r.text
    assert r.json()["kind"] == "validation"
    job = api.job_finished(r.json()["id"], 240)
    assert job["state"] == "done", job
    v = job["validation"]
    assert v["state"] == "done" and v["download"]["bytes"] > 0 and v["download"]["crc32"].startswith("0x")
    cells = v["cells"]
    # 2 x 2 grid: the finer grid is 3 x 3, of which 4 grid points and 5 midpoints
    assert [c["kind"] for c in cells].count("grid") == 4 and [c["kind"] for c in cells].count("midpoint") == 5
    assert {(c["operating_point"]["torque_nm"], c["operating_point"]["speed_rpm"]) for c in cells} == {
        (t, n) for t in (2.0, 2.5, 3.0) for n in (1200.0, 1400.0, 1600.0)
    }
    assert all(c["status"] == "measured" and c["suppression_db"] is not None for c in cells), cells
    # the drive's own feedforward cancels at the points it was trained on (identification reaches >= 40 dB)
    status = {(x["torque_nm"], x["speed_rpm"]): x["status"] for x in m["cells"]}
    assert all(
        c["map_cell_status"] == status[(c["operating_point"]["torque_nm"], c["operating_point"]["speed_rpm"])]
        for c in cells
        if c["kind"] == "grid"
    )
    ok_grid = [c for c in cells if c["kind"] == "grid" and c["map_cell_status"] == "ok"]
    assert ok_grid and all(c["suppression_db"] >= 20.0 for c in ok_grid), ok_grid
    assert v["grid"]["median_db"] is not None and v["midpoint"]["measured"] == 5
    assert v["worst"]["suppression_db"] == min(c["suppression_db"] for c in cells)
    for c in cells:  # the figure is the ratio of the two phasors it reports
        assert c["suppression_db"] == pytest.approx(
            20 * math.log10(c["uncompensated"]["amplitude"] / c["residual"]["amplitude"]), abs=1e-9
        )
        assert c["noise_floor_db"] < 0
    drive_is_safe(emu)

    # the map keeps it, the full cells are one GET away, and every export carries the summary
    m = api.get(f"/maps/{map_id}")
    assert m["validation"]["job_id"] == job["id"] and m["validation"]["grid"]["cells"] == 4
    full = api.get(f"/maps/{map_id}/validation")
    assert full["cells"] == cells
    assert full["options"]["decoupling"] is False  # as the sweep measured the map (the settings' default)
    for fmt, marker in (
        ("csv", "# validated in the drive's LUT mode"),
        ("c", " * validated in the drive's LUT mode"),
        ("dcm", "* validated in the drive's LUT mode"),
    ):
        text = api.http.get(f"/maps/{map_id}/export", params={"format": fmt}).text
        assert marker in text and f"job {job['id']}" in text, (fmt, text[:600])
    exported = api.http.get(f"/maps/{map_id}/export", params={"format": "json"}).json()
    assert exported["validation"]["job_id"] == job["id"]


def test_refusals_lose_nothing(rig, map_id):
    _, api = rig
    assert api.post("/maps/999999/validate").status_code == 404
    assert api.http.post(f"/maps/{map_id}/validate", headers={"Authorization": ""}).status_code == 401
    r = api.post(f"/maps/{map_id}/validate", {"options": {"floor_db": 500}})
    assert r.status_code == 422 and "floor_db" in r.text
    r = api.post(f"/maps/{map_id}/validate", {"forse": True})
    assert r.status_code == 422
    assert api.http.get("/maps/999999/validation").status_code == 404


def faulted_mid_run(emu, api, path: str, body: dict, what: str) -> dict:
    """POST the job, inject an EMCY 0x3210 once its run is under way (the bench busy), and return the finished
    job, failed naming the fault."""
    r = api.post(path, body)
    assert r.status_code == 202, r.text
    api.wait(lambda: api.get("/bench/status")["busy"], 60, f"{what} running")
    assert emu.control({"fault": "emcy", "code": 0x3210})["ok"]
    job = api.job_finished(r.json()["id"], 120)
    assert job["state"] == "failed" and "EMCY 0x3210" in job["error"], job
    return job


def test_a_fault_mid_validation_fails_it_with_the_reason_and_leaves_the_drive_safe(rig, map_id):
    emu, api = rig
    # fault once the run is under way (the drive is in operation for a point)
    job = faulted_mid_run(emu, api, f"/maps/{map_id}/validate", {"force": True}, "validation")
    v = job["validation"]
    assert v["state"] == "failed" and "EMCY 0x3210" in v["error"]
    faulted = [c for c in v["cells"] if c["status"] == "failed"]
    assert len(faulted) == 1 and "EMCY 0x3210" in faulted[0]["error"] and faulted[0]["suppression_db"] is None
    after = v["cells"][v["cells"].index(faulted[0]) + 1 :]
    assert all(c["status"] == "not_measured" and c["suppression_db"] is None for c in after)
    assert len(v["cells"]) == 9
    faults = drive_is_safe(emu)
    assert faults["drive_state"] == "fault"
    # the map keeps this latest (failed) validation, honestly
    assert api.get(f"/maps/{map_id}")["validation"]["state"] == "failed"
    assert api.post("/bench/fault-reset").status_code == 200


def test_cancel_stops_the_validation_and_leaves_the_drive_safe(rig, map_id):
    emu, api = rig
    r = api.post(f"/maps/{map_id}/validate", {"force": True})
    job_id = r.json()["id"]
    api.wait(lambda: api.get("/bench/status")["busy"], 60, "validation running")
    assert api.post(f"/jobs/{job_id}/cancel").status_code == 200
    job = api.job_finished(job_id, 120)
    assert job["state"] == "cancelled", job
    v = job["validation"]
    assert v["state"] == "cancelled"
    assert any(c["status"] == "not_measured" for c in v["cells"])
    assert all(c["suppression_db"] is None for c in v["cells"] if c["status"] != "measured")
    api.wait(lambda: not api.get("/bench/status")["busy"], 30, "bench idle")
    drive_is_safe(emu)


def test_validation_along_runups_judges_every_speed_bin_at_each_torque_row_and_midpoint(rig, map_id):
    """options.runups: at 2, 2.5 and 3 Nm a run-up without and one with the LUT over 1200..1600 rpm; every
    bin a judged point of kind runup (<= 10 rpm apart), with its figures; the summary counts them all."""
    emu, api = rig
    m = api.get(f"/maps/{map_id}")
    r = api.post(f"/maps/{map_id}/validate", {"force": holes(m) > 0, "options": {"runups": True, "target_db": 30}})
    assert r.status_code == 202, r.text
    job = api.job_finished(r.json()["id"], 300)
    assert job["state"] == "done", job
    v = job["validation"]
    bins = [c for c in v["cells"] if c["kind"] == "runup"]
    assert v["torques_run_up"] == [2.0, 2.5, 3.0]
    for torque in (2.0, 2.5, 3.0):
        speeds = sorted(c["operating_point"]["speed_rpm"] for c in bins if c["operating_point"]["torque_nm"] == torque)
        assert speeds[0] <= 1210 and speeds[-1] >= 1590, (torque, speeds[:3], speeds[-3:])
        assert all(0 < b - a <= 10.0 for a, b in zip(speeds, speeds[1:]))
    for c in bins:
        assert c["status"] == "measured" and isinstance(c["holds"], bool)
        # the figure is the ratio of the two run-ups' levels in that bin (an independent recomputation)
        assert c["suppression_db"] == pytest.approx(20 * math.log10(c["uncompensated_fs"] / c["residual_fs"]))
        assert c["holds"] == (c["suppression_db"] >= 30 or c["reason"] is not None and "floor rule" in c["reason"])
        assert c["above_floor_db"] > 20  # the 6th stands far above the noise here
    judged = [c for c in v["cells"] if c["status"] == "measured"]
    assert v["points"] == len(judged) and v["held"] == sum(c["holds"] for c in judged)
    assert v["runup_plant_time_s"] >= 3 * 2 * 4.0  # 3 torques, 2 run-ups of 4 s of ramp each
    drive_is_safe(emu)


def test_a_fault_mid_runup_fails_it_with_the_reason_stores_no_analysis_and_leaves_the_drive_safe(rig):
    """An EMCY while the load ramps (a 30 s ramp: the fault lands inside it): the run-up job fails naming the
    fault, its stored row holds the reason and no figures, the drive is left safe; a person resets."""
    emu, api = rig
    body = {"torque_nm": 2.5, "udc_v": 12, "speed_rpm": [1000, 1600], "rate_rpm_per_s": 20, "orders": [6]}
    job = faulted_mid_run(emu, api, "/runups", body, "run-up")
    result = job["result"]
    assert result["state"] == "failed" and "EMCY 0x3210" in result["error"]
    assert result["speed_rpm"] == [] and result["amplitude"] == []  # a fault never becomes a number
    faults = drive_is_safe(emu)
    assert faults["drive_state"] == "fault"
    assert api.post("/bench/fault-reset").status_code == 200
