"""Fault figures: interlocks and crashes (run: python -m tests.benchmarks.bench_faults, or `make bench`).

The emulator runs in its own process; the service runs as `ripplecal serve --bench FILE` pointed at
it; faults go through the emulator's control socket. Prints:
- fault-to-safe time per fault kind: from the fault (the control socket's reply time, or the SIGSTOP
  of the service) to the drive's power stage going off, both on the emulator's side
  (time.monotonic(), CLOCK_MONOTONIC is system-wide); the fault hits a grid search in flight;
- a frozen database (issue 25): the service on a throwaway PostgreSQL server, its postmaster and its
  backends stopped (SIGSTOP, tests/support/frozen_database.py) while a sweep holds the drive at torque:
  freeze to drive power stage off, the run's silence to power off (the bench watchdog's own figure), and
  SIGTERM to the service's exit while the database stays frozen. The figures of the code before the bench
  watchdog (commit 03eb74f, this script run on that tree) are printed beside them (OLD_FIGURES);
- fault kinds survived: after each fault (and the acknowledgement a person would give), the next
  probe identification succeeds without a restart;
- crash cycles: kill -9 of the service three times during one 16-point sweep, restart, fault reset,
  resume: points lost and points measured twice.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.frozen_database import BackendFreezer
from tests.support.postgres import PostgresCluster
from tests.support.service_process import ServiceProcess

OP1 = {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}
GRID16 = {"torque_nm": [1.0, 1.5, 2.0, 2.5], "speed_rpm": [1500, 1750, 2000, 2250], "udc_v": [12]}
FROZEN_WAIT_S = 30.0  # a drive not off this long after the database froze is reported "none"
TERM_WAIT_S = 30.0  # a service not ended this long after SIGTERM (database frozen) is reported "none", then killed
FROZEN_KIND = "database frozen (PostgreSQL SIGSTOP)"
# measured with this script on commit 03eb74f (before the bench watchdog; `git worktree add /tmp/old 03eb74f`,
# this file and tests/support/frozen_database.py copied in), 2 cores shared with other work; ms, None: never
OLD_FIGURES: dict[str, float | None] = {
    "emcy 0x3210 (drive faults itself)": 0.0,
    "emcy 0x4310 only (drive stays enabled)": 5.0,
    "drive heartbeat missing": 980.0,
    "DAQ disconnect": 5.0,
    "service stalled (SIGSTOP 1.5 s)": 445.0,
    FROZEN_KIND: None,  # the drive stayed at torque for the whole 30 s
}
OLD_FROZEN_TERM_S: float | None = None  # SIGTERM did not end it within 30 s (killed)


def power_off_after(emu: EmulatorRig, t0: float, timeout_s: float = 10.0) -> float | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        off = emu.control({"status": True})["faults"]["drive_power_off_at"]
        if off is not None and off >= t0:
            return off - t0
        time.sleep(0.01)
    return None


def start_run(api: Api) -> int:
    job_id = api.post("/identifications", {"operating_point": OP1, "method": "grid"}).json()["id"]
    api.wait(lambda: api.get("/bench/status")["busy"] and api.get(f"/jobs/{job_id}")["state"] == "running", 60, "run")
    time.sleep(0.3)
    return job_id


def fault_kinds(emu: EmulatorRig, svc: ServiceProcess, api: Api) -> tuple[dict, list, list]:
    times, survived, failed = {}, [], []

    def inject(command):
        return lambda: emu.control(command)["at"]

    def stall():
        t0 = time.monotonic()
        os.kill(svc.proc.pid, signal.SIGSTOP)
        time.sleep(1.5)
        os.kill(svc.proc.pid, signal.SIGCONT)
        return t0

    kinds = [
        ("emcy 0x3210 (drive faults itself)", inject({"fault": "emcy", "code": 0x3210}), None),
        (
            "emcy 0x4310 only (drive stays enabled)",
            inject({"fault": "emcy", "code": 0x4310, "fault_state": False}),
            None,
        ),
        ("drive heartbeat missing", inject({"fault": "heartbeat_stop"}), {"fault": "clear"}),
        ("DAQ disconnect", inject({"fault": "daq_disconnect"}), {"fault": "daq_reconnect"}),
        ("service stalled (SIGSTOP 1.5 s)", stall, None),
        ("SDO delay burst 0.8 s", None, None),
    ]
    for name, fault, recover in kinds:
        job_id = start_run(api)
        if fault is None:  # not a safety trip: survive it, no fault-to-safe time
            emu.control({"fault": "sdo_delay", "seconds": 0.8})
            time.sleep(2.0)
            emu.control({"fault": "clear"})
        else:
            t0 = fault()
            dt = power_off_after(emu, t0)
            times[name] = dt
        job = api.job_finished(job_id, 120)
        if recover:
            emu.control(recover)
            api.wait(lambda: api.get("/bench/status")["daq"]["connected"], 20, "DAQ back")
        time.sleep(0.5)
        api.post("/bench/fault-reset")  # the person's acknowledgement
        ok = all(api.identify(OP1)["state"] == "done" for _ in range(3))
        (survived if ok else failed).append(name)
        print(
            f"  {name:<42} fault-to-safe "
            + (
                "   n/a  "
                if fault is None
                else (f"{times[name] * 1000:6.0f} ms" if times[name] is not None else "  none  ")
            )
            + f"  job {job['state']:<6} ({(job['error'] or '')[:70]}) next 3 jobs {'ok' if ok else 'FAILED'}",
            flush=True,
        )
    return times, survived, failed


def frozen_database(emu: EmulatorRig, workdir: Path) -> tuple[float | None, float | None, float | None]:
    """A sweep at torque on PostgreSQL, the database frozen: (freeze -> drive off, the run's silence -> drive off
    as the bench watchdog reports it (None on a tree without one), SIGTERM -> exit), seconds; None: not within
    FROZEN_WAIT_S / TERM_WAIT_S."""
    cluster = PostgresCluster().init()
    try:
        cluster.start()
        url = cluster.create_database()
        svc = ServiceProcess(url, "--bench", str(emu.bench_file(workdir)), log_dir=workdir)
        freezer = None
        try:
            svc.wait_ready()
            api = Api(svc, url)
            api.post("/bench/fault-reset")
            sweep_id = api.post("/sweeps", {"grid": GRID16, "method": "probe"}).json()["id"]
            api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= 2, 600, "2 points")
            api.wait(
                lambda: emu.control({"status": True})["faults"]["drive_state"] == "operation_enabled", 60, "torque"
            )
            freezer = BackendFreezer(cluster)
            t0 = time.monotonic()
            freezer.freeze()
            to_safe = power_off_after(emu, t0, FROZEN_WAIT_S)
            silence_to_safe = None
            if to_safe is not None:
                watchdog = api.http.get("/bench/status", timeout=10).json().get("watchdog") or {}
                if watchdog.get("silent_since_monotonic") is not None:
                    silence_to_safe = t0 + to_safe - watchdog["silent_since_monotonic"]
            os.killpg(svc.proc.pid, signal.SIGTERM)
            t_term = time.monotonic()
            try:
                svc.proc.wait(TERM_WAIT_S)
                term_s = time.monotonic() - t_term
            except subprocess.TimeoutExpired:
                term_s = None
            api.close()
        finally:
            if freezer is not None:
                freezer.thaw()
            svc.stop()
        return to_safe, silence_to_safe, term_s
    finally:
        cluster.remove()


def crash_cycles(emu: EmulatorRig, workdir: Path, kills_after=(3, 7, 11)) -> tuple[int, int, int]:
    db, bench = workdir / "crash.db", emu.bench_file(workdir)
    sweep_id = None
    for cycle, after in enumerate(list(kills_after) + [None]):
        svc = ServiceProcess(db, "--bench", str(bench))
        svc.wait_ready()
        api = Api(svc, db)
        api.post("/bench/fault-reset")
        if sweep_id is None:
            sweep_id = api.post("/sweeps", {"grid": GRID16, "method": "probe"}).json()["id"]
        else:
            r = api.post(f"/sweeps/{sweep_id}/resume")
            assert r.status_code == 200, r.text
        if after is not None:
            api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["progress"]["done"] >= after, 600, f"{after} points")
            os.killpg(svc.proc.pid, signal.SIGKILL)
            svc.proc.wait(20)
            svc.log.close()
        else:
            sweep = api.wait(
                lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] in ("done", "failed") and s, 900, "done"
            )
            assert sweep["map_id"] is not None, sweep
            svc.stop()
        api.close()
    with sqlite3.connect(db) as conn:
        current = conn.execute(
            "SELECT COUNT(*) FROM results WHERE sweep_id = ? AND superseded_by IS NULL", (sweep_id,)
        ).fetchone()[0]
        twice = conn.execute(
            "SELECT COUNT(*) FROM (SELECT 1 FROM results WHERE sweep_id = ? AND "
            "json_extract(detail_json, '$.discarded') IS NULL GROUP BY torque_nm, speed_rpm, udc_v "
            "HAVING COUNT(*) > 1)",
            (sweep_id,),
        ).fetchone()[0]
    return len(kills_after), 16 - current, twice


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        emu = EmulatorRig()
        try:
            db = workdir / "faults.db"
            svc = ServiceProcess(db, "--bench", str(emu.bench_file(workdir)))
            svc.wait_ready()
            api = Api(svc, db)
            print("fault kinds, each hitting a grid search in flight (emulator in its own process, service --bench):")
            times, survived, failed = fault_kinds(emu, svc, api)
            api.close()
            svc.stop()
            print("a database that hangs under a sweep at torque (service on PostgreSQL):", flush=True)
            frozen_to_safe, silence_to_safe, term_s = frozen_database(emu, workdir)
            times[FROZEN_KIND] = frozen_to_safe
            print(
                f"  {FROZEN_KIND:<42} fault-to-safe "
                + (
                    f"{frozen_to_safe * 1000:6.0f} ms"
                    if frozen_to_safe is not None
                    else f"  none within {FROZEN_WAIT_S:g} s"
                )
                + (
                    f" (the run silent -> safe {silence_to_safe * 1000:.0f} ms)"
                    if silence_to_safe is not None
                    else " (no bench watchdog)"
                )
                + "; SIGTERM -> exit "
                + (f"{term_s:.1f} s" if term_s is not None else f"none within {TERM_WAIT_S:g} s (killed)"),
                flush=True,
            )
            cycles, lost, twice = crash_cycles(emu, workdir)
        finally:
            emu.stop()
    print("fault-to-safe per fault kind, old (commit 03eb74f, before the bench watchdog) and new (this tree):")
    for name, new in times.items():
        if name not in OLD_FIGURES:
            continue
        old = OLD_FIGURES[name]
        print(
            f"  {name:<42} old "
            + (f"{old:6.0f} ms" if old is not None else f"none within {FROZEN_WAIT_S:g} s")
            + "  new "
            + (f"{new * 1000:6.0f} ms" if new is not None else f"none within {FROZEN_WAIT_S:g} s")
        )
    if OLD_FIGURES:
        print(
            f"  {'SIGTERM -> exit, database frozen':<42} old "
            + (f"{OLD_FROZEN_TERM_S:5.1f} s" if OLD_FROZEN_TERM_S is not None else f"none within {TERM_WAIT_S:g} s")
            + "  new "
            + (f"{term_s:5.1f} s" if term_s is not None else f"none within {TERM_WAIT_S:g} s")
        )
    measured = [t for t in times.values() if t is not None]
    print(
        f"fault-to-safe time: worst {max(measured) * 1000:.0f} ms over {len(measured)} fault kinds "
        "(fault -> drive power stage off, emulator's clock)"
    )
    print(
        f"fault kinds survived: {len(survived)} of {len(survived) + len(failed)}"
        + (f" (failed: {', '.join(failed)})" if failed else "")
    )
    print(f"crash cycles: {cycles} x kill -9 during one 16-point sweep: {lost} point(s) lost, {twice} measured twice")
    frozen_safe = times[FROZEN_KIND] is not None and term_s is not None
    return 0 if not failed and lost == 0 and twice == 0 and frozen_safe else 1


if __name__ == "__main__":
    sys.exit(main())
