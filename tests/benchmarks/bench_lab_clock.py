"""A bench PC's clock off by 30 s, behind and ahead (issue 25, finding 4), on a lab's PostgreSQL: what the
other benches see and when the bench's name is free again (run: python -m tests.benchmarks.bench_lab_clock,
or `make bench`).

One observer service (bench A, right clock) and one service for bench C whose clock libfaketime moves
(tests/support/skewed_clock.py). For each skew, printed:
- whether A shows C online while C runs, and how long a second service for C takes to be refused;
- after kill -9 of C: seconds until A shows it offline (this PC's monotonic clock, polled every 0.1 s);
- a restart of C at once after a second kill -9: seconds from the dead instance's last heartbeat to the
  takeover, both stamped by the database (its clock: the one the bound is judged on), and the restart's
  wall time to ready.
Before issue 25 (from the issue, measured then): 30 s behind, shown "not seen since" and its name taken
at once; 30 s ahead, online for 35.5 s after kill -9 and a restart refused for 32 s.
"""

from __future__ import annotations

import os
import signal
import tempfile
import time
from datetime import datetime
from pathlib import Path

import httpx

from tests.support.benches import bench_row, shown
from tests.support.postgres import PostgresCluster
from tests.support.service_process import ServiceProcess, cli, create_token, free_port
from tests.support.skewed_clock import skewed_env
from tests.support.waiting import wait_until

SKEWS_S = (-30, 30)


def serve(url: str, name: str, log_dir: Path, skew_s: int = 0) -> ServiceProcess:
    log_dir.mkdir(parents=True, exist_ok=True)
    env = skewed_env(skew_s) if skew_s else None
    svc = ServiceProcess(url, "--emulate", "--speedup", "0", "--bench-name", name, log_dir=log_dir, env=env)
    try:
        svc.wait_ready(timeout_s=180)
    except BaseException:
        svc.stop()
        raise
    return svc


def kill9(svc: ServiceProcess) -> None:
    os.killpg(svc.proc.pid, signal.SIGKILL)
    svc.proc.wait(20)
    svc.log.close()


def one_skew(url: str, on_a: httpx.Client, skew_s: int, directory: Path) -> dict:
    c = serve(url, "C", directory / "c1", skew_s)
    wait_until(lambda: (b := shown(on_a, "C")) and b["online"], 30, "C online on A", poll_s=0.1)
    t0 = time.monotonic()
    second = cli("serve", "--emulate", "--bench-name", "C", "--db", url, "--port", str(free_port()), check=False)
    refused_s = time.monotonic() - t0
    figures = {"online on A": shown(on_a, "C")["online"], "second refused": second.returncode == 2}
    figures["second refused after s"] = round(refused_s, 2)
    kill9(c)
    t_kill = time.monotonic()
    wait_until(lambda: not shown(on_a, "C")["online"], 120, "C offline on A", poll_s=0.1)
    figures["offline after kill -9 s"] = round(time.monotonic() - t_kill, 2)
    again = serve(url, "C", directory / "c2", skew_s)
    kill9(again)
    dead = bench_row(url, "C")
    t0 = time.monotonic()
    restarted = serve(url, "C", directory / "c3", skew_s)
    figures["restart ready s"] = round(time.monotonic() - t0, 2)
    taken = bench_row(url, "C")
    gap = datetime.fromisoformat(taken["started_at"]) - datetime.fromisoformat(dead["last_seen"])
    figures["heartbeat to takeover s (database clock)"] = round(gap.total_seconds(), 2)
    restarted.stop()
    return figures


def main() -> None:
    cluster = PostgresCluster(durable=True).init()  # as a lab's server runs
    try:
        cluster.start()
        url = cluster.create_database()
        with tempfile.TemporaryDirectory(prefix="bench-lab-clock-") as tmp:
            a = serve(url, "A", Path(tmp) / "a")
            token = create_token(url)
            http = httpx.Client(base_url=a.base + "/api/v1", timeout=60, headers={"Authorization": f"Bearer {token}"})
            try:
                for skew in SKEWS_S:
                    figures = one_skew(url, http, skew, Path(tmp) / f"skew{skew:+d}")
                    print(f"clock {skew:+d} s: " + ", ".join(f"{k}: {v}" for k, v in figures.items()), flush=True)
            finally:
                http.close()
                a.stop()
    finally:
        cluster.remove()


if __name__ == "__main__":
    main()
