"""A lab: several benches, one service per bench, one database (issue 20).

Each `ripplecal serve` holds its bench's name in the `benches` table (migration 0009): it claims the
name at start (refused, naming the holder, while another live instance renews that row), renews
`last_seen` about every second with its bench's state and what it runs, and marks the row stopped on
an orderly stop. Jobs are stored with the bench they are for; each service claims only its own
bench's (Storage.claim_job), so a job posted to any service runs on its bench. `LabWatch` shows the
progress other benches' services write (their rows' `updated_at`) as this service's own events.

A crash leaves the row as it was: it goes stale after `stale_s` (no renewal) and a new instance takes
it over. A restart within that window waits until the old heartbeat has not been renewed for
`stale_s` (a dead process does not renew it), so a restart after kill -9 works at once or within a
few seconds, and a second live service is refused as soon as it sees the first renew its row.

Liveness is judged on one clock for the lab, the database's (issue 25): the heartbeat is stamped by it
and its age computed by it (Storage.claim_bench, get_bench's `seen_s`). A bench PC's clock that is off
(30 s behind or ahead) changes nothing: only this PC's monotonic clock paces the waits here. A holder
that cannot be proven stale by the database's clock is never taken over.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import time
from datetime import datetime, timedelta
from typing import Any

from service.runs.events import EventBroker
from service.store.records import JobRecord, SweepRecord
from service.store.storage import Storage, StorageError

log = logging.getLogger(__name__)

BENCH_STALE_S = 5.0  # a bench whose row was not renewed for this long is offline (and its name free)


class BenchInUse(StorageError):
    """Another live service serves this bench; str() names it (host, port, pid, since)."""


def is_own_bench(bench: str | None, own: str) -> bool:
    """Whether a row or request for `bench` is the service's own: its name, or none (the default in a
    request; rows from before benches, when one database served one bench)."""
    return bench is None or bench == own


def new_instance_id() -> str:
    return secrets.token_hex(8)


def bench_state(status: dict[str, Any], running: str | None = None) -> str:
    """One word for the benches table from the bench's status (service/bench/status.py) and what the
    engine runs (a sweep holds the bench between its points too)."""
    if not status.get("connected"):
        return "disconnected"
    if status.get("error"):
        return "fault"
    return "busy" if status.get("busy") or running else "idle"


def holder_text(row: dict[str, Any]) -> str:
    return f"host {row['host']}, port {row['port']}, pid {row['pid']}, since {row['started_at']}"


class Lab:
    """This service's bench in the lab: its claim, its heartbeat, and what it knows of the other benches."""

    def __init__(
        self,
        storage: Storage,
        bench_name: str,
        instance: str,
        port: int | None,
        version: str,
        stale_s: float = BENCH_STALE_S,
    ):
        self.storage, self.bench_name, self.instance = storage, bench_name, instance
        self.port, self.version, self.stale_s = port, version, stale_s
        self.claimed = False
        self._heartbeat_failing = False

    # --- the claim ---------------------------------------------------------------------------------------
    def claim(self, poll_s: float = 0.5) -> None:
        """Take the bench's name, or BenchInUse naming the live holder. A holder whose row is not renewed
        (a crashed process) is waited out until it is stale by the database's clock; one that renews it
        is alive: refused at once. A row that does not go stale within stale_s (its heartbeat dated ahead
        of the database's clock, by software from before issue 25) cannot be proven dead: refused."""
        row = self._try_claim()
        if row is None:
            return
        seen, holder = row["last_seen"], row["instance"]
        # the row goes stale stale_s after its heartbeat (by the database's clock); a margin covers the
        # database's round trips. Paced by this PC's monotonic clock: its rate counts, never its setting.
        age_s = row["seen_s"] if row["seen_s"] is not None else 0.0
        deadline = time.monotonic() + min(self.stale_s, max(0.0, self.stale_s - age_s)) + 2 * poll_s + 1.0
        while time.monotonic() < deadline:
            time.sleep(poll_s)
            row = self._try_claim()
            if row is None:
                log.warning("bench %s: took over its name from an instance not seen since %s", self.bench_name, seen)
                return
            if row["instance"] != holder or row["last_seen"] != seen:
                break  # its heartbeat was renewed: a live service
        ahead = ""
        if row["seen_s"] is not None and row["seen_s"] < 0:
            ahead = f"; its heartbeat is dated {-row['seen_s']:.1f} s ahead of the database's clock: not provably stale"
        raise BenchInUse(
            f"bench {self.bench_name} is served by another ripplecal serve ({holder_text(row)}; last seen "
            f"{row['last_seen']}{ahead}): stop it first, or give this one another --bench-name"
        )

    def _try_claim(self) -> dict[str, Any] | None:
        row = self.storage.claim_bench(
            {
                "name": self.bench_name,
                "instance": self.instance,
                "host": socket.gethostname(),
                "port": self.port,
                "pid": os.getpid(),
                "software_version": self.version,
            },
            self.stale_s,
        )
        self.claimed = row is None
        return row

    # --- the heartbeat ------------------------------------------------------------------------------------
    def heartbeat(self, state: str, busy: bool, running: str | None) -> None:
        """Renew the row; a failing write is logged once and never reaches the bench."""
        if not self.claimed:
            return
        try:
            if not self.storage.bench_heartbeat(self.bench_name, self.instance, state, busy, running):
                log.error("bench %s: another instance has taken its name over (this one was not seen)", self.bench_name)
            if self._heartbeat_failing:
                log.info("bench %s: heartbeat written again", self.bench_name)
            self._heartbeat_failing = False
        except Exception as exc:  # noqa: BLE001 - the database away must never touch the bench
            if not self._heartbeat_failing:
                log.warning("bench %s: heartbeat not written: %s", self.bench_name, exc)
            self._heartbeat_failing = True

    def stopped(self) -> None:
        if not self.claimed:
            return
        try:
            self.storage.bench_stopped(self.bench_name, self.instance)
        except Exception as exc:  # noqa: BLE001 - the stop goes on: the row goes stale by itself
            log.warning("bench %s: not marked stopped: %s", self.bench_name, exc)
        self.claimed = False

    # --- what the API shows ---------------------------------------------------------------------------------
    def overview(self) -> list[dict[str, Any]]:
        """Every bench the database knows (and those only named by queued jobs), with its queue."""
        queued = self.storage.queued_per_bench()
        rows = {r["name"]: r for r in self.storage.list_benches()}
        out = []
        for name in sorted(set(rows) | set(queued)):
            row = rows.get(name)
            out.append(
                {
                    "name": name,
                    "state": row["state"] if row else "unknown",
                    "last_seen": row["last_seen"] if row else None,
                    "busy": bool(row["busy"]) if row else False,
                    "software_version": row["software_version"] if row else None,
                    "running": row["running"] if row else None,
                    "queue": queued.get(name, 0),
                    "online": self._online(row),
                    "seen": self._seen_text(name, row),
                    "host": row["host"] if row else None,
                    "port": row["port"] if row else None,
                    "own": name == self.bench_name,
                }
            )
        return out

    def waiting_for(self, bench: str | None) -> str | None:
        """What a job for `bench` waits for (None: this service's own bench runs it)."""
        if bench is None or is_own_bench(bench, self.bench_name):
            return None
        row = self.storage.get_bench(bench)
        return f"bench {bench} ({self._seen_text(bench, row)})"

    def _online(self, row: dict[str, Any] | None) -> bool:
        """Renewed within stale_s, by the database's clock (the row's `seen_s`, Storage.get_bench)."""
        if row is None or row["stopped_at"]:
            return False
        return row["seen_s"] is not None and row["seen_s"] <= self.stale_s

    def _seen_text(self, name: str, row: dict[str, Any] | None) -> str:
        if row is None:
            return "never seen: no service has served it"
        if row["stopped_at"]:
            return f"stopped since {row['stopped_at']}"
        if self._online(row):
            return "online"
        return f"not seen since {row['last_seen']}"


class LabWatch:
    """Other benches' progress as this service's events: every second, the jobs and sweeps written since
    the last look by other benches' services, published as the engine publishes its own, with `bench`.
    Rows are stamped (updated_at) and looked for on the database's clock, whatever the bench PCs' clocks
    say. Writes are read back a few seconds (a write stamped before another's commit may become visible
    after it); each is published once."""

    OVERLAP_S = 5.0

    def __init__(self, storage: Storage, broker: EventBroker, own_bench: str):
        self.storage, self.broker, self.own_bench = storage, broker, own_bench
        self._since: str | None = None  # the database's clock at the first look
        self._published: dict[tuple[str, int], str] = {}

    def tick(self) -> None:
        if self._since is None:
            self._since = self.storage.database_now()
        look_from = (datetime.fromisoformat(self._since) - timedelta(seconds=self.OVERLAP_S)).isoformat(
            timespec="milliseconds"
        )
        jobs, sweeps = self.storage.changed_since(look_from)
        for job in jobs:
            if self._fresh("job", job):
                self.broker.publish("job.state", job_event(job))
        for sweep in sweeps:
            if self._fresh("sweep", sweep):
                self.broker.publish("sweep.progress", sweep_event(sweep))
        newest = [r["updated_at"] for r in (*jobs, *sweeps) if r["updated_at"]]
        if newest:
            self._since = max(self._since, max(newest))
        cutoff = look_from
        self._published = {k: v for k, v in self._published.items() if v >= cutoff}

    def _fresh(self, kind: str, row: JobRecord | SweepRecord) -> bool:
        updated_at = row.get("updated_at")
        if is_own_bench(row.get("bench"), self.own_bench) or not updated_at:
            return False  # this service's own engine publishes those as they happen
        key = (kind, row["id"])
        if self._published.get(key) == updated_at:
            return False
        self._published[key] = updated_at
        return True


# the event payloads, one definition for the local engine and the lab watch
def job_event(job: JobRecord) -> dict[str, Any]:
    return {
        "job_id": job["id"],
        "state": job["state"],
        "kind": job["kind"],
        "error": job["error"],
        "bench": job.get("bench"),
    }


def sweep_event(s: SweepRecord) -> dict[str, Any]:
    return {
        "sweep_id": s["id"],
        "kind": s.get("kind") or "sweep",
        "state": s["state"],
        "done": s["done_points"],
        "total": s["total_points"],
        "map_id": s["map_id"],
        "pause_reason": s["pause_reason"],
        "bench": s.get("bench"),
    }
