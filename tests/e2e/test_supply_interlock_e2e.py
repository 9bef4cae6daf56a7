"""The DC supply interlock end to end: the supply drifts, or trips, in the middle of a sweep.

The emulator runs in its own process; the service runs as `ripplecal serve --bench FILE` pointed at it
as at a real bench; the faults go through the emulator's control socket (`supply_voltage`,
`supply_output_off`, `clear`), and the bench's safety is read there too (the drive's state, torque
and injection mode in force). The supply interlock is not latched (service/bench/interlocks.py
SupplyOutOfRange): once the supply is back, a resume goes on without a fault reset unless the drive
itself faulted. Assertions are on states, reasons and counts (never on timings or dB figures).

The emulator runs on a real bench's clock (--speedup 1): the supply interlock reads the supply every
0.5 s of wall time, and at --speedup 0 a whole point takes less than that (a sweep could be measured
before the interlock read the supply once)."""

from __future__ import annotations

import json
import re
import sqlite3

import pytest

from tests.support.bench_rig import served_bench
from tests.support.sweep_checks import assert_points_measured_honestly
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e
GRID = {"torque_nm": [1.5, 2.5], "speed_rpm": [1500, 2000], "udc_v": [12]}
POINTS = 4


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with served_bench(tmp_path_factory.mktemp("supply"), "supply.db", speedup=1.0) as (emu, svc, api, db):
        yield emu, svc, api, db


def sweep_running(api) -> int:
    """A sweep whose first point is stored and whose next one is being measured."""
    r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
    assert r.status_code == 202, r.text
    sweep_id = r.json()["id"]
    api.wait(
        lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 1 and api.get("/bench/status")["busy"],
        what="the second point running",
    )
    return sweep_id


def paused(api, sweep_id: int) -> dict:
    return api.wait(lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] != "running" and s, 120, "sweep paused")


def bench_safe(emu) -> dict | None:
    """The emulator's own view: no power stage, no torque, no injection in force (None: not yet)."""
    s = emu.control({"status": True})["faults"]
    safe = s["drive_state"] != "operation_enabled" and s["drive_torque_nm"] == 0.0 and s["drive_injection_mode"] == 0
    return s if safe else None


def results(db, sweep_id: int) -> list[dict]:
    with sqlite3.connect(db) as conn:
        conn.row_factory = sqlite3.Row
        return [dict(r) for r in conn.execute("SELECT * FROM results WHERE sweep_id = ? ORDER BY id", (sweep_id,))]


def discarded_for(rows: list[dict], interlock: str) -> list[dict]:
    return [
        r
        for r in rows
        if json.loads(r["detail_json"]).get("discarded") == "interlock"
        and json.loads(r["detail_json"])["interlock"]["interlock"] == interlock
    ]


def resume_and_finish(emu, api, db, sweep_id: int) -> dict:
    """Resume at once (no fault reset first, as a script or `auto_resume` would), then the sweep finishes
    with every point measured once."""
    r = api.post(f"/sweeps/{sweep_id}/resume")
    assert r.status_code == 200, r.text

    def ended():
        s = api.get(f"/sweeps/{sweep_id}")
        return (s["state"] in ("done", "failed") or s["state"] == "paused" and s["pause_reason"]) and s

    sweep = api.wait(ended, 300, "sweep finished")
    supply = emu.control({"status": True})["faults"]["supply"]
    assert sweep["state"] == "done", (
        f"{sweep['state']}: {sweep.get('pause_reason')}; the emulated supply now: {supply} (a supply trip named "
        "while the supply is back at its setpoint is the previous run's: service/bench/interlocks.py keeps an "
        "armed-only interlock's reason across runs)"
    )
    assert sweep["progress"]["done"] == POINTS and len(sweep["points"]) == POINTS and sweep["map_id"] is not None
    assert_points_measured_honestly(sweep["points"], min_ok=POINTS - 1)
    # one current result per point; every discarded attempt superseded by the attempt that replaced it
    rows = results(db, sweep_id)
    current = [r for r in rows if r["superseded_by"] is None]
    assert sorted((r["torque_nm"], r["speed_rpm"]) for r in current) == sorted(
        (t, n) for t in GRID["torque_nm"] for n in GRID["speed_rpm"]
    )
    assert all(
        r["superseded_by"] is not None and r["status"] != "ok"
        for r in rows
        if json.loads(r["detail_json"]).get("discarded")
    )
    return sweep


def test_supply_drifting_mid_sweep_pauses_it_safe_and_resume_finishes_it(rig):
    emu, svc, api, db = rig
    sweep_id = sweep_running(api)
    assert emu.control({"fault": "supply_voltage", "volts": 9.0})["ok"]
    try:
        sweep = paused(api, sweep_id)
        assert sweep["state"] == "paused", sweep
        reason = sweep["pause_reason"]
        found = re.search(r"DC supply out of range: measures (\d+\.\d\d) V, set 12\.00 V", reason)
        assert found and abs(float(found[1]) - 9.0) < 0.1, reason
        assert "resume when it has cleared" in reason
        # the bench is safe: drive not enabled, torque 0, injection off (the emulator's own state)
        wait_until(lambda: bench_safe(emu), 60.0, "the bench safe")
        assert not api.get("/bench/status")["busy"]
        # the point in flight was discarded: stored failed, never ok, naming the supply
        discarded = discarded_for(results(db, sweep_id), "supply")
        assert discarded and all(r["status"] != "ok" and "DC supply out of range" in r["error"] for r in discarded)
        assert sweep["progress"]["done"] < POINTS
    finally:
        assert emu.control({"fault": "clear"})["ok"]
    # not latched, and the drive did not fault (drive_firmware.py has no under-voltage trip): no reset needed
    assert emu.control({"status": True})["faults"]["drive_state"] != "fault"
    resume_and_finish(emu, api, db, sweep_id)


def test_supply_tripping_mid_sweep_pauses_it_safe_naming_what_happened(rig):
    """The output drops to 0 V: the drive's power stage loses its DC link (drive_firmware.py: power only
    with U_dc >= udc_min_v). Whatever the service sees first, the supply interlock or the drive's
    reaction, the pause names it and the bench is left safe; once the supply is back, the sweep finishes."""
    emu, svc, api, db = rig
    sweep_id = sweep_running(api)
    assert emu.control({"fault": "supply_output_off"})["ok"]
    try:
        sweep = paused(api, sweep_id)
        assert sweep["state"] == "paused", sweep
        reason = sweep["pause_reason"]
        found = re.search(r"DC supply out of range: measures (\d+\.\d\d) V, set 12\.00 V", reason)
        drive_reacted = re.search(r"(drive|DC link|under-?voltage)", reason, re.IGNORECASE)
        assert (found and float(found[1]) < 0.5) or drive_reacted, reason
        supply = wait_until(lambda: bench_safe(emu), 60.0, "the bench safe")["supply"]
        assert supply["tripped"] and supply["actual_v"] == 0.0
        discarded = [r for r in results(db, sweep_id) if json.loads(r["detail_json"]).get("discarded")]
        assert discarded and all(r["status"] != "ok" for r in discarded)
    finally:
        assert emu.control({"fault": "clear"})["ok"]
    if api.get("/bench/status")["drive"]["state"] == "fault":  # a drive reaction is acknowledged by a person
        assert api.post("/bench/fault-reset").status_code == 200
    resume_and_finish(emu, api, db, sweep_id)  # the run switches the output on again (set_dc_link)
