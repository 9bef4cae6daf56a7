"""A database that hangs never holds the bench at torque (issue 25, finding 2): `ripplecal serve --bench
... --db postgresql://...` on an emulated bench at speedup 1 (real time), a 5 x 5 sweep; once it has points
stored, the service's PostgreSQL backends are frozen (SIGSTOP, and every new one as it appears:
tests/support/frozen_database.py) while the drive runs at torque. Then:
- the bench watchdog disables drive and load within 5 s of the run's loop going silent on the database
  (the emulator's own clock of its power stage going off), and says why (bench status, log);
- a GET answers within a few seconds (503 naming the database), never hangs;
- cancel answers within a few seconds and the bench stays safe (the run does not start again);
- SIGTERM ends the service within 10 s, bench safe;
- no point lost: after SIGCONT, the points stored before the freeze are in the database, and a restarted
  service shows the sweep stopped (not running), those points kept.
And a SIGTERM right after the freeze disables the drive at once (the signal's first reaction, not the
watchdog's bound for a silent run), the service ended within 10 s."""

from __future__ import annotations

import os
import signal
import time

import pytest

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.frozen_database import BackendFreezer
from tests.support.service_process import ServiceProcess
from tests.support.storage_trouble import drive_safe
from tests.support.sweep_checks import results_per_point

pytestmark = pytest.mark.e2e

GRID = {"torque_nm": [0.5, 1.0, 1.5, 2.0, 2.5], "speed_rpm": [1000, 1250, 1500, 1750, 2000], "udc_v": [12]}
SAFE_WITHIN_S = 5.0  # the bound: drive disabled this long after the run waits on the database
ANSWER_WITHIN_S = 10.0  # "a few seconds": the statement bound (5 s) and the client's margin, with room for load
TERM_WITHIN_S = 10.0


@pytest.fixture
def emu():
    rig = EmulatorRig(speedup=1.0)
    yield rig
    rig.stop()


def faults(emu: EmulatorRig) -> dict:
    return emu.control({"status": True})["faults"]


def stored_points(api: Api, sweep_id: int) -> set[tuple]:
    points = api.get(f"/sweeps/{sweep_id}")["points"]
    return {
        (p["operating_point"]["torque_nm"], p["operating_point"]["speed_rpm"], p["operating_point"]["udc_v"])
        for p in points
        if p.get("result") is not None
    }


def timed(call) -> tuple[object, float]:
    t0 = time.monotonic()
    out = call()
    return out, time.monotonic() - t0


def sweep_at_torque(svc: ServiceProcess, emu: EmulatorRig, pg_url: str) -> tuple[Api, int, set[tuple]]:
    """The service ready, a 5 x 5 sweep with 2 points stored and the drive at torque: (api, sweep id, the
    points stored)."""
    svc.wait_ready()
    api = Api(svc, pg_url)
    assert api.post("/bench/fault-reset").status_code == 200
    sweep_id = api.post("/sweeps", {"grid": GRID, "method": "probe"}).json()["id"]
    api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 2, 600, "2 points stored")
    api.wait(lambda: faults(emu)["drive_state"] == "operation_enabled", 60, "the drive at torque")
    before = stored_points(api, sweep_id)
    assert len(before) >= 2
    return api, sweep_id, before


def test_a_frozen_database_leaves_the_bench_safe_cancel_and_sigterm_act_and_no_point_is_lost(
    emu, pg_cluster, pg_url, tmp_path
):
    bench = emu.bench_file(tmp_path)
    svc = ServiceProcess(pg_url, "--bench", str(bench), log_dir=tmp_path)
    freezer = None
    try:
        api, sweep_id, before = sweep_at_torque(svc, emu, pg_url)
        freezer = BackendFreezer(pg_cluster)
        t_freeze = time.monotonic()
        assert freezer.freeze() >= 1, "no backend of the service to freeze"

        # the run's loop goes silent at its next database call (the end of the point in flight); the watchdog
        # then disables the drive, timed on the emulator's clock (CLOCK_MONOTONIC, system-wide)
        off_at = api.wait(
            lambda: (
                (f := faults(emu))["drive_power_off_at"] is not None
                and f["drive_power_off_at"] >= t_freeze
                and f["drive_power_off_at"]
            ),
            120,
            "the drive's power stage off after the freeze",
        )
        status = api.get("/bench/status")  # the bench's status needs no database
        watchdog = status["watchdog"]
        assert watchdog["last_stop"] is not None and "did not report" in watchdog["last_stop"]["reason"], watchdog
        assert "stuck at " in watchdog["last_stop"]["reason"], watchdog  # where the worker waited, named
        silent_since = watchdog["silent_since_monotonic"]
        assert silent_since is not None and off_at - silent_since <= SAFE_WITHIN_S, (
            f"drive off {off_at - silent_since:.2f} s after the run went silent ({off_at - t_freeze:.2f} s after "
            "the freeze)"
        )
        api.wait(lambda: drive_safe(emu) and faults(emu)["load_state"] != "operation_enabled", 10, "load disabled")

        r, get_s = timed(lambda: api.http.get(f"/sweeps/{sweep_id}"))
        assert r.status_code == 503 and "database" in r.json()["detail"], r.text
        assert get_s < ANSWER_WITHIN_S, f"GET took {get_s:.1f} s"

        r, cancel_s = timed(lambda: api.post(f"/sweeps/{sweep_id}/cancel"))
        assert r.status_code in (200, 503), r.text
        assert cancel_s < ANSWER_WITHIN_S, f"cancel took {cancel_s:.1f} s"
        time.sleep(3.0)  # the run must not start again after the cancel
        assert drive_safe(emu), faults(emu)

        os.killpg(svc.proc.pid, signal.SIGTERM)
        t_term = time.monotonic()
        svc.proc.wait(timeout=TERM_WITHIN_S + 20)
        ended_s = time.monotonic() - t_term
        assert ended_s <= TERM_WITHIN_S, f"SIGTERM ended the service after {ended_s:.1f} s"
        assert drive_safe(emu), faults(emu)
        print(
            f"frozen database: drive off {off_at - silent_since:.2f} s after the run went silent "
            f"({off_at - t_freeze:.2f} s after the freeze); GET answered in {get_s:.1f} s, cancel in {cancel_s:.1f} s; "
            f"SIGTERM to exit {ended_s:.1f} s"
        )
        log = svc.log_text()
        assert "bench watchdog" in log, log[-3000:]
        api.close()
    finally:
        if freezer is not None:
            freezer.thaw()
        svc.stop()

    # no point lost: what was stored before the freeze is in the database once it answers again
    assert before <= set(results_per_point(pg_url, sweep_id)), results_per_point(pg_url, sweep_id)
    (tmp_path / "again").mkdir()
    again = ServiceProcess(pg_url, "--bench", str(bench), log_dir=tmp_path / "again")
    try:
        again.wait_ready()
        api = Api(again, pg_url)
        sweep = api.get(f"/sweeps/{sweep_id}")
        assert sweep["state"] in ("interrupted", "cancelled"), sweep
        assert before <= stored_points(api, sweep_id)
        api.close()
    finally:
        again.stop()


def test_sigterm_makes_the_bench_safe_at_once_while_the_database_hangs(emu, pg_cluster, pg_url, tmp_path):
    """SIGTERM acts on the bench at once, whatever the worker does: the drive off well before the watchdog's
    bound for a silent run could have passed, and the service ends within 10 s with the database frozen."""
    svc = ServiceProcess(pg_url, "--bench", str(emu.bench_file(tmp_path)), log_dir=tmp_path)
    freezer = None
    try:
        api, _, _ = sweep_at_torque(svc, emu, pg_url)
        bound_s = api.get("/bench/status")["watchdog"]["bound_s"]
        freezer = BackendFreezer(pg_cluster)
        assert freezer.freeze() >= 1, "no backend of the service to freeze"
        t_term = time.monotonic()  # before the signal: the service may act on it before killpg returns here
        os.killpg(svc.proc.pid, signal.SIGTERM)
        off_at = api.wait(
            lambda: (
                (f := faults(emu))["drive_power_off_at"] is not None
                and f["drive_power_off_at"] >= t_term
                and f["drive_power_off_at"]
            ),
            30,
            "the drive's power stage off after SIGTERM",
        )
        assert off_at - t_term < bound_s, (
            f"drive off {off_at - t_term:.2f} s after SIGTERM (watchdog bound {bound_s} s)"
        )
        svc.proc.wait(timeout=TERM_WITHIN_S + 20)
        ended_s = time.monotonic() - t_term
        assert ended_s <= TERM_WITHIN_S, f"SIGTERM ended the service after {ended_s:.1f} s"
        assert drive_safe(emu) and faults(emu)["load_state"] != "operation_enabled", faults(emu)
        print(f"SIGTERM, database frozen: drive off after {off_at - t_term:.2f} s, service ended after {ended_s:.1f} s")
        api.close()
    finally:
        if freezer is not None:
            freezer.thaw()
        svc.stop()
