"""A sweep through storage trouble, whatever the trouble (tests/e2e/test_storage_trouble_e2e.py: a lock,
a read-only or full filesystem under SQLite; tests/e2e/test_postgres_outage_e2e.py: a PostgreSQL server
stopped): the service started on the emulated bench with a short busy timeout, and the checks that the
sweep waits with the bench safe and finishes by itself, every point measured exactly once."""

from __future__ import annotations

import tempfile
from pathlib import Path

import httpx

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.service_process import ServiceProcess

GRID = {"torque_nm": [1.5, 2.0, 2.5], "speed_rpm": [1500, 2000], "udc_v": [12]}


def start(emu: EmulatorRig, db: Path | str, monkeypatch) -> tuple[ServiceProcess, Api]:
    monkeypatch.setenv("RIPPLECAL_SERVER__DB_BUSY_TIMEOUT_S", "1")  # unavailable after 1 s, not 10
    # the raw recordings on another filesystem: the trouble here is the database's (and a recording being
    # written, open, would keep Linux from remounting the database's filesystem read-only)
    monkeypatch.setenv("RIPPLECAL_RECORDINGS__DIRECTORY", str(Path(tempfile.mkdtemp(prefix="ripplecal-rec-"))))
    # the log beside the test, not on the database's filesystem (an open file would keep it from going read-only)
    logs = Path(tempfile.mkdtemp(prefix="ripplecal-log-"))
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(logs)), log_dir=logs)
    svc.wait_ready()
    api = Api(svc, db)
    assert api.post("/bench/fault-reset").status_code == 200  # whatever an earlier test left
    return svc, api


def drive_safe(emu: EmulatorRig) -> bool:
    f = emu.control({"status": True})["faults"]
    return f["drive_state"] != "operation_enabled" and f["drive_torque_nm"] == 0.0 and f["drive_injection_mode"] == 0


def waits_for_the_database(r: httpx.Response) -> bool:
    """The API says the sweep waits for the database: a 503 with Retry-After and a JSON reason naming the
    database where it cannot be read (a lock, a read-only filesystem, a server stopped); where it can still
    be read (a full disk reads while SQLite's WAL index file stays), the sweep shown paused with the database
    as the reason. Either way the file is named by its name, never an absolute path."""
    if r.status_code == 503:
        assert r.headers.get("Retry-After") and "database" in r.json()["detail"], r.text
        assert " /" not in r.json()["detail"], r.text
        return True
    assert r.status_code == 200, r.text
    sweep = r.json()
    if sweep["state"] != "paused" or "database" not in (sweep["pause_reason"] or ""):
        return False
    assert " /" not in sweep["pause_reason"], sweep["pause_reason"]
    return True


def said_waiting(api: Api, sweep_id: int, keep_on=None) -> bool:
    """`waits_for_the_database` of the sweep's answer, after `keep_on()` (trouble that must be kept up)."""
    if keep_on is not None:
        keep_on()
    return waits_for_the_database(api.http.get(f"/sweeps/{sweep_id}"))


def sweep_through(api: Api, emu: EmulatorRig, trouble_on, trouble_off, keep_on=None) -> dict:
    """A sweep; once it has 2 points, `trouble_on()`; while the database is away: the API says the sweep
    waits for it (`waits_for_the_database`), the bench goes safe; then `trouble_off()`: the sweep finishes by
    itself, every point measured exactly once. `keep_on()` is called at every look until the sweep waits: a
    full disk gets space back when SQLite deletes its WAL file, and is filled again."""
    sweep_id = api.post("/sweeps", {"grid": GRID, "method": "probe"}).json()["id"]
    api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 2, 300, "2 points")
    trouble_on()
    try:
        api.wait(lambda: said_waiting(api, sweep_id, keep_on), 60, "the sweep said waiting for the database")
        api.wait(lambda: drive_safe(emu), 60, "the bench made safe while the database is away")
    finally:
        trouble_off()
    sweep = api.wait(
        lambda: (
            (r := api.http.get(f"/sweeps/{sweep_id}")).status_code == 200
            and r.json()["state"] in ("done", "failed", "cancelled")
            and r.json()
        ),
        300,
        "sweep finished",
    )
    assert sweep["state"] == "done", sweep
    assert sweep["progress"]["done"] == sweep["progress"]["total"] == 6 and len(sweep["points"]) == 6
    history = api.get(f"/sweeps/{sweep_id}")["points"]
    assert len({(p["operating_point"]["torque_nm"], p["operating_point"]["speed_rpm"]) for p in history}) == 6
    return sweep
