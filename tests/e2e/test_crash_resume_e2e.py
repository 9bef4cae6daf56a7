"""Issue 8 end to end: a sweep survives kill -9 and SIGTERM of the service; the emulator child of
`serve --emulate` never outlives the service. The emulator runs in its own process and the service
is pointed at it with `--bench`, as at a real bench; a real SQLite file is shared by the restarts."""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import pytest

from tests.support.bench_rig import Api, EmulatorRig, alive, children_of
from tests.support.operating_points import OP1
from tests.support.service_process import ServiceProcess
from tests.support.sweep_checks import assert_points_measured_honestly, results_per_point

pytestmark = pytest.mark.e2e
GRID16 = {"torque_nm": [1.0, 1.5, 2.0, 2.5], "speed_rpm": [1500, 1750, 2000, 2250], "udc_v": [12]}


@pytest.fixture(scope="module")
def emu():
    rig = EmulatorRig()
    yield rig
    rig.stop()


def kill9(svc: ServiceProcess) -> None:
    os.killpg(svc.proc.pid, signal.SIGKILL)
    svc.proc.wait(20)
    svc.log.close()


def second_pass_only_where_the_first_missed(db, sweep_id) -> None:
    with sqlite3.connect(db) as conn:
        rows = conn.execute(
            "SELECT torque_nm, speed_rpm, udc_v, status, "
            "COALESCE(json_extract(detail_json, '$.details.sweep_pass'), 1) FROM results WHERE sweep_id = ?",
            (sweep_id,),
        ).fetchall()
    first_ok = {r[:3] for r in rows if r[4] == 1 and r[3] == "ok"}
    again = [r[:3] for r in rows if r[4] == 2]
    assert not first_ok & set(again) and len(again) == len(set(again)), rows


def test_kill9_after_5_of_16_points_then_resume_measures_only_the_rest(emu, tmp_path):
    db, bench = tmp_path / "crash.db", emu.bench_file(tmp_path)
    svc = ServiceProcess(db, "--bench", str(bench))
    svc.wait_ready()
    api = Api(svc, db)
    assert api.post("/bench/fault-reset").status_code == 200  # whatever an earlier test left on the shared drive
    r = api.post("/sweeps", {"grid": GRID16, "method": "probe"})
    assert r.status_code == 202, r.text
    sweep_id = r.json()["id"]
    api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 5, 300, "5 points")
    kill9(svc)
    api.close()
    before = results_per_point(db, sweep_id, first_pass_only=True)
    assert len(before) >= 5

    svc = ServiceProcess(db, "--bench", str(bench))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        sweep = api.get(f"/sweeps/{sweep_id}")
        assert sweep["state"] == "interrupted" and "stopped" in sweep["pause_reason"]
        assert sweep["progress"]["done"] == len(before)
        # the drive lost the dead service's heartbeat and went to FAULT: a person acknowledges first
        refused = api.post(f"/sweeps/{sweep_id}/resume")
        assert refused.status_code == 409 and "heartbeat lost" in refused.text and "fault-reset" in refused.text
        assert api.post("/bench/fault-reset").status_code == 200
        assert api.post(f"/sweeps/{sweep_id}/resume").status_code == 200
        sweep = api.wait(
            lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] in ("done", "failed") and s, 400, "sweep done"
        )
        assert sweep["state"] == "done" and sweep["map_id"] is not None
        assert sweep["progress"]["done"] == 16 and sweep["progress"]["total"] == 16
        assert len(sweep["points"]) == 16
        assert_points_measured_honestly(sweep["points"], min_ok=12)
        after = results_per_point(db, sweep_id, first_pass_only=True)
        assert len(after) == 16 and set(after.values()) == {1}  # none lost, none measured twice
        second_pass_only_where_the_first_missed(db, sweep_id)
        assert len(api.get(f"/maps/{sweep['map_id']}")["cells"]) == 16
        api.close()
    finally:
        svc.stop()


def test_sigterm_leaves_the_sweep_interrupted_with_the_reason(emu, tmp_path):
    db, bench = tmp_path / "term.db", emu.bench_file(tmp_path)
    svc = ServiceProcess(db, "--bench", str(bench))
    svc.wait_ready()
    api = Api(svc, db)
    # the previous service's exit stopped its heartbeat, so the shared drive may be in FAULT
    assert api.post("/bench/fault-reset").status_code == 200
    sweep_id = api.post("/sweeps", {"grid": GRID16, "method": "probe"}).json()["id"]
    sweep = api.wait(
        lambda: (
            (s := api.get(f"/sweeps/{sweep_id}"))["progress"]["done"] >= 1
            or s["state"] != "running"
            and s["state"] != "queued"
            and s
        ),
        300,
        "1 point",
    )
    assert api.get(f"/sweeps/{sweep_id}")["state"] == "running", sweep
    api.close()
    svc.stop()  # SIGTERM to the process group
    with sqlite3.connect(db) as conn:
        state, reason = conn.execute("SELECT state, pause_reason FROM sweeps WHERE id = ?", (sweep_id,)).fetchone()
    assert state == "interrupted" and "SIGTERM" in reason
    # the emulator (another process) was left safe: drive not enabled
    assert emu.control({"status": True})["faults"]["drive_state"] != "operation_enabled"


def test_serve_emulate_leaves_no_emulator_after_kill9(tmp_path):
    svc = ServiceProcess(tmp_path / "e.db", "--emulate")
    svc.wait_ready()
    emulators = children_of(svc.proc.pid)
    assert emulators, "serve --emulate started no child"
    os.kill(svc.proc.pid, signal.SIGKILL)  # the service alone (its own process group would hide a leak)
    svc.proc.wait(20)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(alive(pid) for pid in emulators):
        time.sleep(0.1)
    left = [pid for pid in emulators if alive(pid)]
    for pid in left:  # do not leak into the next test, then fail
        os.kill(pid, signal.SIGKILL)
    svc.log.close()
    assert not left, f"emulator(s) {left} outlived the service"


def test_an_orderly_stop_needs_no_reset_and_kill9_still_faults(emu, tmp_path):
    """SIGTERM: drive and load disabled, then their heartbeat consumers disarmed before the service's
    heartbeat stops, so the next start runs at once; kill -9 leaves them in FAULT and the refusal says
    how to reset; a fault reset right after the restart works."""
    db, bench = tmp_path / "restart.db", emu.bench_file(tmp_path)
    svc = ServiceProcess(db, "--bench", str(bench))
    svc.wait_ready()
    api = Api(svc, db)
    assert api.post("/bench/fault-reset").status_code == 200  # whatever an earlier test left on the shared drive
    assert emu.control({"status": True})["faults"]["drive_heartbeat_consumer_ms"] > 0  # armed at connect
    assert api.identify(OP1)["state"] == "done"
    api.close()
    svc.stop()  # SIGTERM
    faults = emu.control({"status": True})["faults"]
    assert faults["drive_heartbeat_consumer_ms"] == 0 and faults["load_heartbeat_consumer_ms"] == 0, faults
    assert faults["drive_state"] == "switch_on_disabled" and faults["load_state"] == "switch_on_disabled", faults

    svc = ServiceProcess(db, "--bench", str(bench))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        assert api.get("/bench/status")["interlocks"]["tripped"] == []
        job = api.identify(OP1)  # at once: no reset asked for
        assert job["state"] == "done" and job["result"]["status"] == "ok", job
        assert emu.control({"status": True})["faults"]["drive_heartbeat_consumer_ms"] > 0  # armed again
        api.close()
    finally:
        kill9(svc)
    # the dead service's heartbeat is missed: both devices fault (the drive within its 500 ms consumer time)
    api.wait(lambda: emu.control({"status": True})["faults"]["drive_state"] == "fault", 30, "drive FAULT")

    svc = ServiceProcess(db, "--bench", str(bench))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        job = api.identify(OP1)
        assert job["state"] == "failed" and "fault-reset" in job["error"], job
        r = api.post("/bench/fault-reset")  # right after the restart
        assert r.status_code == 200, r.text
        job = api.identify(OP1)
        assert job["state"] == "done" and job["result"]["status"] == "ok", job
        api.close()
    finally:
        svc.stop()


def test_kill9_during_a_validation_keeps_the_points_measured_and_names_the_lut_in_the_drive(emu, tmp_path):
    db = tmp_path / "validation.db"
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(tmp_path)))
    svc.wait_ready()
    api = Api(svc, db)
    assert api.post("/bench/fault-reset").status_code == 200  # whatever an earlier test left on the shared drive
    r = api.post(
        "/sweeps", {"grid": {"torque_nm": [2.0, 3.0], "speed_rpm": [1200, 1600], "udc_v": [12]}, "method": "probe"}
    )
    sweep = api.wait(
        lambda: (s := api.get(f"/sweeps/{r.json()['id']}"))["state"] in ("done", "failed") and s, 300, "sweep done"
    )
    map_id = sweep["map_id"]
    job_id = api.post(f"/maps/{map_id}/validate", {"force": True}).json()["id"]
    # the validation is stored as it measures: running, with its cells growing
    partial = api.wait(
        lambda: (
            (v := api.http.get(f"/maps/{map_id}/validation")).status_code == 200
            and len(v.json()["cells"]) >= 2
            and v.json()
        ),
        300,
        "two points stored",
    )
    assert partial["state"] == "running" and partial["download"]["map_id"] == map_id
    kill9(svc)
    api.close()
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(tmp_path)))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        v = api.get(f"/maps/{map_id}/validation")
        assert v["state"] == "failed" and len(v["cells"]) >= len(partial["cells"]), v
        assert f"the drive holds the LUT of map {map_id}" in v["error"] and v["download"]["crc32"] in v["error"]
        job = api.get(f"/jobs/{job_id}")
        assert job["state"] == "failed" and f"LUT of map {map_id}" in job["error"], job
        api.close()
    finally:
        svc.stop()
