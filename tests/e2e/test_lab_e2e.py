"""Issue 20 end to end: a lab of two benches on one PostgreSQL database, one `ripplecal serve --emulate
--bench-name` per bench (each its own emulator), as bench PCs in a lab run them. A run posted to either
service runs on the bench it names; both benches sweep at once; A's event stream shows B's progress;
pause and resume asked at A are done by B's service; maps and tokens are the lab's; a kill -9
of one service leaves the other's sweep running, and the restarted one resumes its own sweep, each
point measured once; a second service for a bench that is served is refused, naming the first."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading

import httpx
import pytest

from service.store.storage import Storage
from tests.support.service_process import ServiceProcess, cli, create_token, free_port
from tests.support.sweep_checks import results_per_point
from tests.support.waiting import wait_run_finished, wait_until

pytestmark = pytest.mark.e2e
GRID12 = {"torque_nm": [1.0, 1.5, 2.0], "speed_rpm": [1250, 1500, 1750, 2000], "udc_v": [12]}
GRID25 = {"torque_nm": [0.5, 1.0, 1.5, 2.0, 2.5], "speed_rpm": [1000, 1250, 1500, 1750, 2000], "udc_v": [12]}
GRID6 = {"torque_nm": [1.0, 1.5, 2.0], "speed_rpm": [1500, 2000], "udc_v": [12]}


def serve(url: str, name: str, log_dir) -> ServiceProcess:
    log_dir.mkdir(exist_ok=True)
    svc = ServiceProcess(url, "--emulate", "--speedup", "0", "--bench-name", name, log_dir=log_dir)
    svc.wait_ready()
    return svc


def client(svc: ServiceProcess, token: str) -> httpx.Client:
    return httpx.Client(base_url=svc.base + "/api/v1", timeout=30, headers={"Authorization": f"Bearer {token}"})


def sweep(http: httpx.Client, grid: dict, bench: str | None = None) -> int:
    body = {"grid": grid, "method": "probe", **({"bench": bench} if bench else {})}
    r = http.post("/sweeps", json=body)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def finished(http: httpx.Client, sweep_id: int, timeout_s: float = 400.0) -> dict:
    return wait_run_finished(lambda: http.get(f"/sweeps/{sweep_id}").json(), timeout_s, f"sweep {sweep_id}")


class EventLog:
    """sweep.progress events of a service's /events (SSE), collected in a thread until closed."""

    def __init__(self, http: httpx.Client):
        self.events: list[dict] = []
        self._stream = http.stream("GET", "/events", timeout=httpx.Timeout(60.0))
        self._response = self._stream.__enter__()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        kind = None
        try:
            for line in self._response.iter_lines():
                if line.startswith("event: "):
                    kind = line[len("event: ") :]
                elif line.startswith("data: ") and kind == "sweep.progress":
                    self.events.append(json.loads(line[len("data: ") :]))
        except (httpx.HTTPError, RuntimeError):
            pass  # closed

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._stream.__exit__(None, None, None)


def measured_spans(url: str, sweep_id: int) -> list[tuple[str, str]]:
    """(started_at, finished_at) of every result of the sweep (UTC ISO: they compare as text)."""
    storage = Storage(url)
    try:
        with storage.connect() as conn:
            rows = conn.execute(
                "SELECT started_at, finished_at FROM results WHERE sweep_id = ?", (sweep_id,)
            ).fetchall()
            return [(r[0], r[1]) for r in rows]
    finally:
        storage.close()


def overlapping(a: list[tuple[str, str]], b: list[tuple[str, str]]) -> bool:
    return any(s1 < e2 and s2 < e1 for s1, e1 in a for s2, e2 in b)


def claimed_by(url: str, sweep_id: int) -> set[str]:
    """The service instances that ran the sweep's jobs (the benches table names each instance's bench)."""
    storage = Storage(url)
    try:
        with storage.connect() as conn:
            rows = conn.execute("SELECT claimed_by FROM jobs WHERE sweep_id = ?", (sweep_id,)).fetchall()
            return {r[0] for r in rows}
    finally:
        storage.close()


def instance_of(url: str, bench: str) -> str:
    storage = Storage(url)
    try:
        return storage.get_bench(bench)["instance"]
    finally:
        storage.close()


def test_two_benches_on_one_postgresql_database(pg_url, tmp_path):
    a = serve(pg_url, "A", tmp_path / "a")
    b = serve(pg_url, "B", tmp_path / "b")
    token = create_token(pg_url)  # made once for the lab: every service knows it
    on_a, on_b = client(a, token), client(b, token)
    try:
        benches = {x["name"]: x for x in on_a.get("/benches").json()}
        assert benches["A"]["online"] and benches["B"]["online"], benches
        assert benches["A"]["own"] and not benches["B"]["own"]
        # a second service for bench B while B runs: refused before it touches anything, naming the first
        refused = cli(
            "serve", "--emulate", "--bench-name", "B", "--db", pg_url, "--port", str(free_port()), check=False
        )
        assert refused.returncode == 2, refused.stderr
        line = refused.stderr.strip().splitlines()[-1]
        assert "bench B is served by another ripplecal serve" in line and f"port {b.port}" in line, line
        assert "pid" in line and "since" in line, line

        # a sweep posted to A for bench B runs on B, while A sweeps its own bench at the same time
        seen_on_a = EventLog(on_a)
        for_b = sweep(on_a, GRID12, bench="B")
        own_a = sweep(on_a, GRID12)
        done_b, done_a = finished(on_b, for_b), finished(on_a, own_a)
        assert done_b["state"] == "done" and done_a["state"] == "done", (done_b, done_a)
        assert done_b["progress"]["done"] == 12 and done_a["progress"]["done"] == 12
        assert done_b["bench"] == "B" and done_a["bench"] == "A"
        # the two benches measured at the same time: points of the two sweeps overlap in wall time
        assert overlapping(measured_spans(pg_url, for_b), measured_spans(pg_url, own_a))
        assert claimed_by(pg_url, for_b) == {instance_of(pg_url, "B")}
        assert claimed_by(pg_url, own_a) == {instance_of(pg_url, "A")}
        # A's event stream showed B's progress (A never ran it: read from the database, tagged with its bench)
        wait_until(
            lambda: any(e["sweep_id"] == for_b and e["state"] == "done" for e in seen_on_a.events),
            10,
            "B's sweep done on A's events",
        )
        seen_on_a.close()
        shown = [e for e in seen_on_a.events if e["sweep_id"] == for_b]
        assert shown and {e["bench"] for e in shown} == {"B"}, shown
        # both services list every map of the lab
        maps = {done_a["map_id"], done_b["map_id"]}
        for http in (on_a, on_b):
            assert maps <= {m["id"] for m in http.get("/maps").json()}

        # pause and resume asked at A for B's sweep: written for B's service, which acts within about a second
        paused_b = sweep(on_a, GRID25, bench="B")  # long enough to be paused between its points
        assert on_a.post(f"/sweeps/{paused_b}/pause").json()["control_request"] == "pause"
        wait_until(lambda: on_b.get(f"/sweeps/{paused_b}").json()["state"] == "paused", 30, "B paused", poll_s=0.1)
        assert on_a.post(f"/sweeps/{paused_b}/resume").json()["control_request"] == "resume"
        resumed_b = finished(on_b, paused_b)
        assert resumed_b["state"] == "done" and resumed_b["progress"]["done"] == 25, resumed_b

        # kill -9 of A's service (and its emulator) in the middle of its sweep: B's sweep runs to its end
        crash_a, long_b = sweep(on_a, GRID6), sweep(on_b, GRID6)
        wait_until(lambda: on_a.get(f"/sweeps/{crash_a}").json()["progress"]["done"] >= 2, 300, "2 points on A")
        os.killpg(a.proc.pid, signal.SIGKILL)
        a.proc.wait(20)
        a.log.close()
        assert finished(on_b, long_b)["state"] == "done"
        # its row is no longer renewed: offline within the stale limit (5 s), said with when it was last seen
        gone = wait_until(
            lambda: next((x for x in on_b.get("/benches").json() if x["name"] == "A" and not x["online"]), None),
            15,
            "bench A offline",
            poll_s=0.5,
        )
        assert gone["seen"].startswith("not seen since"), gone

        # A restarted (within the stale limit: it waits until the dead instance's row goes stale)
        a = serve(pg_url, "A", tmp_path / "a2")
        on_a.close()
        on_a = client(a, token)
        interrupted = on_a.get(f"/sweeps/{crash_a}").json()
        assert interrupted["state"] == "interrupted", interrupted
        assert on_a.post(f"/sweeps/{crash_a}/resume").status_code == 200
        resumed = finished(on_a, crash_a)
        assert resumed["state"] == "done" and resumed["progress"]["done"] == 6, resumed
        per_point = results_per_point(pg_url, crash_a, first_pass_only=True)
        assert len(per_point) == 6 and set(per_point.values()) == {1}, per_point
        assert on_b.get(f"/sweeps/{long_b}").json()["state"] == "done"  # B's rows untouched by A's recovery
    finally:
        on_a.close()
        on_b.close()
        for svc in (a, b):
            svc.stop()
