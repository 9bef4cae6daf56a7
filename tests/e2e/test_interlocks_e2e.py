"""Issue 8 end to end: interlocks, fault reset by a person, recovery without a restart.

The emulator runs in its own process; the service runs as `ripplecal serve --bench FILE` pointed at
it as at a real bench; faults go through the emulator's control socket. Assertions are on states,
reasons and counts (never on timings or dB figures)."""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import pytest

from service.store.storage import Storage
from tests.support.bench_rig import served_bench
from tests.support.operating_points import OP1
from tests.support.stored_maps import stored_map
from tests.support.sweep_checks import assert_points_measured_honestly

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with served_bench(tmp_path_factory.mktemp("interlocks"), "i.db") as (emu, svc, api, db):
        yield emu, svc, api, db


def busy(api) -> bool:
    return api.get("/bench/status")["busy"]


def drive_state(emu) -> str:
    """The drive's state as the emulator has it (its control socket: no SDO, no service involved)."""
    return emu.control({"status": True})["faults"]["drive_state"]


def test_emcy_mid_sweep_pauses_until_fault_reset_then_resume_completes(rig):
    emu, svc, api, db = rig
    r = api.post(
        "/sweeps", {"grid": {"torque_nm": [1.5, 2.5], "speed_rpm": [1500, 2000], "udc_v": [12]}, "method": "probe"}
    )
    assert r.status_code == 202, r.text
    sweep_id = r.json()["id"]
    api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 1 and busy(api), what="second point running")
    assert emu.control({"fault": "emcy", "code": 0x3210})["ok"]

    sweep = api.wait(lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] == "paused" and s, 60, "sweep paused")
    assert "EMCY 0x3210 DC link over-voltage" in sweep["pause_reason"]
    assert "fault-reset" in sweep["pause_reason"]
    # the faulted attempt (if torque was commanded for it) is stored failed, never ok
    faulted = [p for p in sweep["points"] if "EMCY 0x3210" in (p["error"] or "")]
    assert all(p["state"] == "failed" for p in faulted)
    assert sweep["progress"]["done"] == len([p for p in sweep["points"] if p not in faulted])

    # the status shows the state the run left at once (read at the run's end, not at the next poll)
    assert api.get("/bench/status")["drive"]["state"] == "fault"
    # the drive stays in FAULT: nothing resets it by itself, no run starts, resume is refused
    time.sleep(1.5)  # deliberately: time for the 1 Hz status poller and the monitor to (not) reset it
    status = api.get("/bench/status")
    assert status["drive"]["state"] == "fault" and "EMCY 0x3210" in status["error"]
    assert not status["busy"]
    refused = api.post(f"/sweeps/{sweep_id}/resume")
    assert refused.status_code == 409 and "EMCY 0x3210" in refused.text
    assert api.get("/bench/status")["drive"]["state"] == "fault"

    # a viewer may not acknowledge; an operator does
    assert api.http.post("/bench/fault-reset", headers={"Authorization": ""}).status_code == 401
    r = api.post("/bench/fault-reset")
    assert r.status_code == 200, r.text
    assert r.json()["reset"]["drive"] is True and r.json()["still_tripped"] is None
    assert r.json()["status"]["drive"]["state"] == "switch_on_disabled"

    assert api.post(f"/sweeps/{sweep_id}/resume").status_code == 200
    sweep = api.wait(
        lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] in ("done", "failed") and s, 240, "sweep done"
    )
    assert sweep["state"] == "done" and sweep["map_id"] is not None
    assert sweep["progress"]["done"] == 4 and len(sweep["points"]) == 4
    assert all("EMCY" not in (p["error"] or "") for p in sweep["points"])
    # every point measured again, honestly (ok means its target met)
    assert_points_measured_honestly(sweep["points"], min_ok=3)
    # history: the discarded attempt points at the attempt that replaced it
    with sqlite3.connect(db) as conn:
        rows = conn.execute(
            "SELECT status, superseded_by, error FROM results WHERE sweep_id = ?", (sweep_id,)
        ).fetchall()
    discarded = [r for r in rows if r[2] and "EMCY 0x3210" in r[2]]
    assert all(r[0] != "ok" and r[1] is not None for r in discarded)
    assert len(rows) == 4 + len(discarded)


def test_daq_disconnect_and_reconnect_at_the_same_path(rig):
    emu, svc, api, _ = rig
    assert emu.control({"fault": "daq_disconnect"})["ok"]
    status = api.wait(lambda: (s := api.get("/bench/status"))["daq"]["connected"] is False and s, 10, "DAQ shown lost")
    assert "DAQ" in status["error"] and "disconnected" in status["error"]
    job = api.identify(OP1, timeout_s=60)
    assert job["state"] == "failed" and "refused: interlock tripped: DAQ" in job["error"]
    # nothing was commanded: a fresh reading of the drive (the status keeps the last one with its age;
    # the one from the previous test's run may still be shown until the next 1 Hz poll)
    api.wait(
        lambda: (
            (d := api.get("/bench/status")["drive"]).get("ages", {}).get("state", 99) < 1.5
            and d["state"] != "operation_enabled"
        ),
        15,
        "a fresh drive reading, not operation_enabled",
    )
    reply = emu.control({"fault": "daq_reconnect"})
    assert reply["ok"] and reply["daq"] == emu.endpoints["daq"]  # same stable path
    status = api.wait(lambda: (s := api.get("/bench/status"))["daq"]["connected"] and s, 10, "DAQ shown back")
    assert status["daq"]["reconnects"] >= 1
    job = api.identify(OP1)
    assert job["state"] == "done", job


def test_a_burst_of_sdo_delays_fails_at_most_the_job_it_hit(rig):
    emu, svc, api, _ = rig
    r = api.post("/identifications", {"operating_point": OP1, "method": "probe"})
    job_id = r.json()["id"]
    api.wait(lambda: busy(api) or api.get(f"/jobs/{job_id}")["state"] != "queued", 60, "job running")
    assert emu.control({"fault": "sdo_delay", "seconds": 0.8})["ok"]
    time.sleep(2.0)  # deliberately: the burst lasts 2 s, held while the job runs
    assert emu.control({"fault": "clear"})["ok"]
    api.job_finished(job_id)
    for _ in range(3):
        job = api.identify(OP1)
        assert job["state"] == "done", job


def test_slow_sdo_answers_never_make_an_idle_bench_busy(rig):
    """The 1 Hz status poller reads the drive without the run lock: with every SDO answer 0.15 s late
    (a slow CAN link), fault-reset and a LUT download on an idle bench are never refused as busy."""
    emu, svc, api, db = rig
    map_id = stored_map(Storage(db))
    assert emu.control({"fault": "sdo_delay", "seconds": 0.15})["ok"]
    try:
        for _ in range(3):  # each some 30 SDO exchanges, interleaved with the poller's reads
            r = api.post("/bench/fault-reset")
            assert r.status_code == 200, r.text
        r = api.post(f"/maps/{map_id}/download")  # its SDO writes take a while at this delay
        assert r.status_code == 200, r.text
    finally:
        assert emu.control({"fault": "clear"})["ok"]
    assert api.identify(OP1)["state"] == "done"


def test_a_move_on_a_slow_link_is_a_run_at_work_not_a_stall(rig):
    """Every SDO answer 0.25 s late: the move to the point writes and polls some 30 objects without a guard
    check between them, longer than the watchdog's 3 s bound. Each answered transfer is the run's loop at
    work (service/bench/watchdog.py bus_answered): the run is not stopped as stuck (it was, 'stuck at
    cia402_master.py in write')."""
    emu, svc, api, _ = rig
    stop_before = api.get("/bench/status")["watchdog"]["last_stop"]
    assert emu.control({"fault": "sdo_delay", "seconds": 0.25})["ok"]
    try:
        job = api.identify(OP1, "probe", timeout_s=240)
    finally:
        assert emu.control({"fault": "clear"})["ok"]
    assert job["state"] == "done", (job.get("error"), job.get("result"))
    assert job["result"]["status"] == "ok", job["result"]["error"]
    assert api.get("/bench/status")["watchdog"]["last_stop"] == stop_before


def test_heartbeat_lost_by_a_stalled_service_names_the_cause(rig):
    """The service process stops (SIGSTOP) long enough for the drive's consumer heartbeat to lapse:
    the drive goes safe by itself; the job's error names the heartbeat as the first cause."""
    emu, svc, api, _ = rig
    r = api.post("/identifications", {"operating_point": OP1, "method": "grid"})
    job_id = r.json()["id"]
    api.wait(lambda: busy(api), 60, "job running")
    api.wait(lambda: drive_state(emu) == "operation_enabled", 60, "the drive running the grid search")
    os.kill(svc.proc.pid, signal.SIGSTOP)
    try:
        # deliberately: the service stalls longer than the drive's consumer heartbeat time (0.5 s) and
        # the monitor's stall_s (0.5 s), so the heartbeat lapses and the service learns why
        time.sleep(1.5)
        api.wait(lambda: drive_state(emu) == "fault", 30, "the drive in FAULT (its heartbeat consumer lapsed)")
    finally:
        os.kill(svc.proc.pid, signal.SIGCONT)
    job = api.job_finished(job_id, 60)
    assert job["state"] == "failed" and "heartbeat lost" in job["error"], job["error"]
    assert "bench made safe" in job["error"] or "make_safe failed" in job["error"]
    assert api.post("/bench/fault-reset").status_code == 200
    assert api.identify(OP1)["state"] == "done"
