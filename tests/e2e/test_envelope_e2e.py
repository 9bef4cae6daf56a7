"""Issue 25 finding 3 end to end: the envelope held on what the motor does.

The emulator runs in its own process, paced at real time (speedup 1: a trip's timing is the bench's); the service
is `ripplecal serve --bench FILE` pointed at it. The TRUE torque comes from the emulator's scope on its control
socket (the service never reads it). Past about 3270 rpm at 12 V the paper bench's back-EMF exceeds what the DC link
holds even with full field weakening: the current controller sits in its voltage limit and the machine brakes
uncontrolled at about twice i_max, whatever torque is asked for (the emulator models it).

Assertions are on states, reasons and the scope's record; how long the true torque stays over the limit is a
figure of tests/benchmarks/bench_envelope.py (the bound here only catches a trip that did not happen)."""

from __future__ import annotations

import sqlite3

import pytest

from service.settings import load_settings
from tests.support.bench_rig import served_bench
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e

LIMIT_NM = 5.0  # safety.max_torque_nm of the default settings
SCOPE_SAMPLES = 65536  # 4.1 s at 16 kHz: the whole move to the point and its trip
RUNAWAY = {"torque_nm": -2.5, "speed_rpm": 5000, "udc_v": 12}  # the point


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with served_bench(tmp_path_factory.mktemp("envelope"), "envelope.db", speedup=1.0) as (emu, svc, api, db):
        yield emu, svc, api, db


@pytest.fixture(autouse=True)
def bench_left_ready(rig):
    """After each test, whatever it asserted: its sweep ended and a latched trip acknowledged, so one test's
    failure does not fail the next ones with a refused bench."""
    yield
    _, _, api, _ = rig
    for sweep in api.get("/sweeps"):
        if sweep["state"] in ("queued", "running", "paused"):
            api.post(f"/sweeps/{sweep['id']}/cancel")
    wait_until(lambda: not api.get("/bench/status")["busy"], 60, "bench idle")
    api.post("/bench/fault-reset")


def drive_state(emu) -> str:
    return emu.control({"status": True})["faults"]["drive_state"]


def scope_torque(emu, timeout_s: float = 60.0) -> list[float]:
    """The true torque (Nm, one sample per control period) of the scope's record, once complete."""
    reply = wait_until(lambda: (r := emu.control({"scope": "read"}))["ready"] and r, timeout_s, "scope record")
    return reply["channels"]["torque_nm"]


def stored_results(db) -> list[dict]:
    with sqlite3.connect(db) as conn:
        conn.row_factory = sqlite3.Row
        return [dict(r) for r in conn.execute("SELECT status, torque_nm, torque_actual_nm, error FROM results")]


def test_points_outside_the_envelope_are_refused_up_front_with_the_reason(rig):
    emu, _, api, _ = rig
    before = emu.control({"status": True})["faults"]["plant_samples"]
    for op in (RUNAWAY, {**RUNAWAY, "torque_nm": 2.5}, {"torque_nm": 5.0, "speed_rpm": 6000, "udc_v": 12}):
        r = api.post("/identifications", {"operating_point": op, "method": "probe"})
        assert r.status_code == 422, r.text
        [item] = r.json()["detail"]
        assert item["type"] == "value_error.envelope" and item["loc"] == ["body", "operating_point", "speed_rpm"]
        assert "back-EMF exceeds what the DC link holds (up to 3266 rpm at 12 V)" in item["msg"]
        assert "override_envelope_model" in item["msg"]
    # a grid with no point inside is refused (one with some inside runs those: the clipped sweep test below)
    sweep = {"grid": {"torque_nm": [2.5], "speed_rpm": [5000, 6000]}, "method": "probe"}
    r = api.post("/sweeps", sweep)
    assert r.status_code == 422 and "back-EMF" in r.text and "every one of the 2 point(s)" in r.text, r.text
    preview = api.post("/sweeps/preview", sweep).json()
    assert preview["accepted"] is False and preview["problems"] == r.json()["detail"]
    assert api.get("/jobs") == [] and api.get("/sweeps") == []  # nothing queued, the drive never enabled
    assert drive_state(emu) == "switch_on_disabled" and not api.get("/bench/status")["busy"]
    assert emu.control({"status": True})["faults"]["plant_samples"] >= before


def test_with_the_override_the_actuals_interlock_trips_and_leaves_the_bench_safe(rig):
    emu, _, api, db = rig
    assert emu.control({"scope": "arm", "samples": SCOPE_SAMPLES})["ok"]
    r = api.post(
        "/identifications",
        {"operating_point": RUNAWAY, "method": "probe", "options": {"override_envelope_model": True}},
    )
    assert r.status_code == 202, r.text
    job = api.job_finished(r.json()["id"], 120)
    assert job["state"] == "failed", job
    assert "interlock tripped: the motor left the envelope: current actual" in job["error"], job["error"]
    assert "bench made safe" in job["error"]
    torque = scope_torque(emu)
    over = [abs(t) > LIMIT_NM for t in torque]
    # the record holds the runaway (the torque reversed against the command) and its end (power off)
    assert min(torque) < -1.0, min(torque)
    assert all(abs(t) < 0.05 for t in torque[-1600:]), "the drive still produces torque at the record's end"
    # a bound that only catches a missing trip (the figure is the benchmark's): the issue saw 1.45 s
    assert sum(over) / 16_000 < 0.5, f"true torque over {LIMIT_NM} Nm for {sum(over) / 16:.0f} ms"
    assert drive_state(emu) == "switch_on_disabled"
    status = wait_until(lambda: (s := api.get("/bench/status"))["busy"] is False and s, 30, "bench idle")
    assert status["load"]["state"] != "operation_enabled"
    # latched: a person looks at a machine that ran away before the next run
    assert "the motor left the envelope" in (status.get("error") or ""), status
    r = api.post("/identifications", {"operating_point": {"torque_nm": 2.0, "speed_rpm": 1500}, "method": "probe"})
    assert r.status_code == 202
    refused = api.job_finished(r.json()["id"], 60)
    assert refused["state"] == "failed" and "refused: interlock tripped" in refused["error"]
    reset = api.post("/bench/fault-reset")
    assert reset.status_code == 200 and reset.json()["still_tripped"] is None, reset.text
    # the discarded point is no result at the torque it ran away to
    assert all(r["status"] != "ok" for r in stored_results(db) if r["torque_nm"] == RUNAWAY["torque_nm"])


def test_a_sweep_that_runs_away_pauses_with_the_reason_and_keeps_what_it_measured(rig):
    """Overridden, a sweep moves on from a point within the envelope to the issue's: the trip pauses it with the
    reason (the existing interlock machinery), the point in flight is discarded, the first point keeps its result."""
    emu, _, api, _ = rig
    body = {
        "grid": {"torque_nm": [-2.5], "speed_rpm": [2000, 5000], "udc_v": [12]},
        "method": "probe",
        "options": {"override_envelope_model": True},
    }
    r = api.post("/sweeps", body)
    assert r.status_code == 202, r.text
    sweep_id = r.json()["id"]
    sweep = api.wait(
        lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] not in ("queued", "running") and s, 180, "sweep stopped"
    )
    assert sweep["state"] == "paused" and "the motor left the envelope" in sweep["pause_reason"], sweep
    by_speed = {p["operating_point"]["speed_rpm"]: p for p in sweep["points"]}
    # kept as measured: ok, or below_target on a loaded PC at speedup 1 (CI saw it), never the trip's
    first = by_speed[2000.0]
    assert first["state"] in ("ok", "below_target"), by_speed
    assert "left the envelope" not in (first.get("error") or "") + (first.get("reason") or ""), first
    assert 5000.0 not in by_speed or by_speed[5000.0]["state"] != "ok"
    wait_until(lambda: not api.get("/bench/status")["busy"], 30, "bench idle")
    assert drive_state(emu) == "switch_on_disabled"
    assert api.post(f"/sweeps/{sweep_id}/cancel").status_code == 200
    assert api.post("/bench/fault-reset").json()["still_tripped"] is None


def test_a_result_records_its_torque_and_is_never_ok_away_from_its_command(rig):
    """2 Nm at 3000 rpm, 12 V: the drive holds at most 1.19 Nm there (refused up front); overridden, the firmware
    runs at its most-torque point, within every hard limit (no trip), and the result says the torque it ran at."""
    emu, _, api, db = rig
    away = {"operating_point": {"torque_nm": 2.0, "speed_rpm": 3000, "udc_v": 12}, "method": "probe"}
    assert api.post("/identifications", away).status_code == 422
    r = api.post("/identifications", {**away, "options": {"override_envelope_model": True}})
    assert r.status_code == 202, r.text
    job = api.job_finished(r.json()["id"], 180)
    result = job["result"]
    assert result["status"] == "failed" and result["torque_actual_nm"] is not None
    assert abs(result["torque_actual_nm"] - 1.19) < 0.2, result["torque_actual_nm"]
    assert "the motor ran at 1.1" in result["error"] and "not at its command of 2 Nm" in result["error"]
    # a point within the envelope: ok, and it says the torque it ran at
    r = api.post("/identifications", {"operating_point": {"torque_nm": 2.5, "speed_rpm": 2000}, "method": "probe"})
    good = api.job_finished(r.json()["id"], 180)["result"]
    # its status is the identification's (ok, or below_target on a loaded PC at speedup 1): never a departure
    assert good["status"] in ("ok", "below_target") and abs(good["torque_actual_nm"] - 2.5) < 0.2, good
    assert "the motor ran at" not in (good.get("error") or "") + (good.get("reason") or ""), good
    # no result stored ok at a torque that left its command
    safety = load_settings(environ={}).safety
    for row in stored_results(db):
        if row["status"] == "ok":
            tolerance = max(safety.torque_tolerance_fraction * abs(row["torque_nm"]), safety.torque_tolerance_nm)
            assert row["torque_actual_nm"] is not None and abs(row["torque_actual_nm"] - row["torque_nm"]) <= tolerance


def test_a_sweep_clipped_by_the_envelope_runs_only_the_points_inside(rig):
    """A grid over the whole range (as a test engineer writes one): the points the envelope model refuses are
    stored failed with the reason and never run (the load never goes there); the points inside are measured."""
    emu, _, api, _ = rig
    body = {"grid": {"torque_nm": [2.5], "speed_rpm": [2000, 5000], "udc_v": [12]}, "method": "probe"}
    preview = api.post("/sweeps/preview", body).json()
    assert preview["accepted"] and [c["operating_point"]["speed_rpm"] for c in preview["not_run"]] == [5000.0]
    r = api.post("/sweeps", body)
    assert r.status_code == 202, r.text
    sweep_id, fastest_rpm = r.json()["id"], 0.0

    def finished():
        nonlocal fastest_rpm  # the emulator's own speed, read while the sweep runs
        fastest_rpm = max(fastest_rpm, abs(emu.control({"status": True})["faults"]["drive_speed_rpm"]))
        s = api.get(f"/sweeps/{sweep_id}")
        return s["state"] not in ("queued", "running") and s

    sweep = wait_until(finished, 180, "sweep finished")
    assert sweep["state"] == "done", sweep
    by_speed = {p["operating_point"]["speed_rpm"]: p for p in sweep["points"]}
    assert by_speed[2000.0]["state"] == "ok" and by_speed[5000.0]["state"] == "failed", by_speed
    result = by_speed[5000.0]["result"]
    assert result["error"].startswith("not run: ") and "back-EMF exceeds what the DC link holds" in result["error"]
    assert result["torque_actual_nm"] is None
    assert drive_state(emu) != "fault"
    assert 1500 < fastest_rpm < 3000, fastest_rpm  # it ran at 2000 rpm and never went towards 5000
