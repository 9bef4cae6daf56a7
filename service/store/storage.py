"""Storage: the repository functions the service uses, over one of two engines chosen by the `--db`
string (service/store/engines.py): a SQLite file (the embedded default) or a PostgreSQL server (a lab).
The SQL is written once, with `?` placeholders; where the engines differ it asks the engine's dialect
(service/store/dialect.py). Numbered migrations (service/store/migrations.py); every write in one
transaction, so a failure in one operating point never touches the results of others."""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import secrets
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, cast

from service.store.engines import open_engine
from service.store.errors import StorageError, StorageUnavailable
from service.store.migrations import MIGRATIONS_DIR, load_migrations
from service.store.records import (
    JobRecord,
    MapRecord,
    MapSummaryRecord,
    ResultRecord,
    ScheduleRecord,
    ScheduleRunRecord,
    SweepRecord,
    ValidationRecord,
)

__all__ = ["Storage", "StorageError", "StorageUnavailable", "now_iso", "MIGRATIONS_DIR"]


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class Storage:
    def __init__(self, path: str | Path, busy_timeout_s: float = 10.0, statement_timeout_s: float | None = None):
        """`path`: a SQLite file, or a `postgresql://user@host:port/dbname` URL (service/store/engines.py).
        `busy_timeout_s`: how long a call waits for another's lock (or the server's pool) before it says so;
        `statement_timeout_s`: a server's bound on one statement (default: the engine's)."""
        self.engine = open_engine(path, busy_timeout_s, statement_timeout_s)
        self.dialect = self.engine.dialect
        self.path = self.engine.path  # the SQLite file (None on a server)
        self.location = self.engine.location  # the database as the log and the CLI name it (no password)
        # a sweep's committed results: current (not superseded) and not discarded by an interlock
        # (detail_json "discarded" names why; the attempt stays as history and the point is measured again)
        self._committed = (
            f"sweep_id = ? AND superseded_by IS NULL AND {self.dialect.json_text('detail_json', 'discarded')} IS NULL"
        )
        self._known_tokens: dict[
            str, str
        ] = {}  # sha256 -> role of tokens seen valid (used while the database is unavailable)
        try:
            self.migrate()
        except BaseException:
            self.engine.close()
            raise

    @contextlib.contextmanager
    def connect(self) -> Iterator[Any]:
        """A connection (every statement its own transaction); an error that passes (a lock, a read-only
        or full filesystem, a lost server) becomes StorageUnavailable, here and in the caller's use of it."""
        with self.engine.connect() as conn:
            yield conn

    def known_unavailable(self) -> StorageUnavailable | None:
        """Why the database's last call failed, while no call has succeeded since (None: not known to be
        away; SQLite's calls answer quickly either way): what must answer at once need not wait on it again."""
        known = getattr(self.engine, "known_unavailable", None)
        return known() if known is not None else None

    @contextlib.contextmanager
    def transaction(self) -> Iterator[Any]:
        """A connection in one transaction, committed when the block ends, rolled back if it raises."""
        with self.engine.transaction() as conn:
            yield conn

    def migrate(self) -> int:
        """Apply the migrations the database has not seen (service/store/migrations.py); its schema version."""
        return self.engine.migrate(load_migrations(self.dialect.name))

    @property
    def busy_timeout_s(self) -> float:
        """How long a call waits for another's lock before the database counts as unavailable."""
        return self.engine.busy_timeout_s

    @busy_timeout_s.setter
    def busy_timeout_s(self, value: float) -> None:
        self.engine.busy_timeout_s = value  # SQLite reads it per connection; a server's pool keeps its own

    @property
    def files_directory(self) -> Path:
        """Where files that belong with the database go by default (recordings)."""
        return self.engine.files_directory

    def close(self) -> None:
        """Let go of the engine's connections (a server's pool); nothing to do on SQLite."""
        self.engine.close()

    # --- tokens ------------------------------------------------------------------------------------
    def create_token(self, role: str, label: str = "") -> tuple[int, str]:
        token = "rc_" + secrets.token_urlsafe(32)
        with self.transaction() as conn:
            cur = conn.execute(
                "INSERT INTO api_tokens (role, token_sha256, label, created_at) VALUES (?, ?, ?, ?)",
                (role, _sha256(token), label, now_iso()),
            )
            return _new_id(cur), token

    def revoke_token(self, token_id: int) -> bool:
        with self.transaction() as conn:
            cur = conn.execute(
                "UPDATE api_tokens SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL", (now_iso(), token_id)
            )
            return _one_row(cur)

    def token_role(self, token: str) -> str | None:
        """The token's role (None: unknown or revoked). While the database is unavailable, a token this
        process has seen valid before stays valid (an operator can still cancel or pause; revoking one
        needs the database anyway)."""
        digest = _sha256(token)
        if digest in self._known_tokens and self.known_unavailable() is not None:
            return self._known_tokens[digest]  # an operator's cancel is not held for the database's timeout
        try:
            with self.connect() as conn:
                row = conn.execute(
                    "SELECT role FROM api_tokens WHERE token_sha256 = ? AND revoked_at IS NULL", (digest,)
                ).fetchone()
        except StorageUnavailable:
            if digest in self._known_tokens:
                return self._known_tokens[digest]
            raise
        role = row["role"] if row else None
        if role is None:
            self._known_tokens.pop(digest, None)
        else:
            self._known_tokens[digest] = role
        return role

    def list_tokens(self) -> list[dict[str, Any]]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute("SELECT id, role, label, created_at, revoked_at FROM api_tokens ORDER BY id")
            ]

    # --- jobs --------------------------------------------------------------------------------------
    def create_job(
        self,
        kind: str,
        request: dict[str, Any],
        sweep_id: int | None = None,
        bench: str | None = None,
        claimed_by: str | None = None,
    ) -> int:
        """`bench`: the bench it is for; `claimed_by`: the service instance that runs it (None: whichever
        service serves `bench` takes it from the database, Storage.claim_job)."""
        now = now_iso()
        with self.transaction() as conn:
            return _new_id(
                conn.execute(
                    "INSERT INTO jobs (kind, state, request_json, sweep_id, created_at, bench, claimed_by, updated_at) "
                    f"VALUES (?, 'queued', ?, ?, ?, ?, ?, {self.dialect.now_text})",
                    (kind, json.dumps(request), sweep_id, now, bench, claimed_by),
                )
            )

    def update_job(self, job_id: int, **fields: Any) -> None:
        _update(self, "jobs", job_id, fields)

    def get_job(self, job_id: int) -> JobRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            return _record(row) if row else None

    def list_jobs(self, limit: int = 100) -> list[JobRecord]:
        with self.connect() as conn:
            return [_record(r) for r in conn.execute("SELECT * FROM jobs ORDER BY id DESC LIMIT ?", (limit,))]

    # --- sweeps ------------------------------------------------------------------------------------
    def create_sweep(
        self,
        method: str,
        harmonic_order: int,
        grid: dict[str, Any],
        options: dict[str, Any],
        total: int,
        bench_identity: str,
        software_version: str,
        schedule_id: int | None = None,
        kind: str = "sweep",
        source_map_id: int | None = None,
        refinement: dict[str, Any] | None = None,
        bench: str | None = None,
    ) -> int:
        """A sweep, or (kind `refinement`) a map's refinement: its state in `refinement` (service/runs/refinement.py)."""
        with self.transaction() as conn:
            return _new_id(
                conn.execute(
                    "INSERT INTO sweeps (state, method, harmonic_order, grid_json, options_json, total_points, bench_identity, "
                    "software_version, created_at, schedule_id, kind, source_map_id, refinement_json, bench, updated_at) "
                    f"VALUES ('queued', ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, {self.dialect.now_text})",
                    (
                        method,
                        harmonic_order,
                        json.dumps(grid),
                        json.dumps(options),
                        total,
                        bench_identity,
                        software_version,
                        now_iso(),
                        schedule_id,
                        kind,
                        source_map_id,
                        json.dumps(refinement) if refinement is not None else None,
                        bench,
                    ),
                )
            )

    def update_sweep(self, sweep_id: int, **fields: Any) -> None:
        _update(self, "sweeps", sweep_id, fields)

    def get_sweep(self, sweep_id: int) -> SweepRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM sweeps WHERE id = ?", (sweep_id,)).fetchone()
            return _record(row) if row else None

    def list_sweeps(self, limit: int = 100) -> list[SweepRecord]:
        with self.connect() as conn:
            return [_record(r) for r in conn.execute("SELECT * FROM sweeps ORDER BY id DESC LIMIT ?", (limit,))]

    # --- results -----------------------------------------------------------------------------------
    def insert_result(self, row: dict[str, Any]) -> int:
        """One result in its own transaction. A sweep's result supersedes the earlier attempts at the
        same operating point (kept as history, results.superseded_by) and the sweep's progress
        counters are recounted from its current results, in the same transaction, so a crash between
        two statements cannot leave a point counted twice or a point with two current results."""
        with self.transaction() as conn:
            rid = _insert(conn, "results", row)
            if row.get("sweep_id") is not None:
                conn.execute(
                    "UPDATE results SET superseded_by = ? WHERE sweep_id = ? AND torque_nm = ? AND speed_rpm = ? "
                    "AND udc_v = ? AND superseded_by IS NULL AND id != ?",
                    (rid, row["sweep_id"], row["torque_nm"], row["speed_rpm"], row["udc_v"], rid),
                )
                conn.execute(
                    f"UPDATE sweeps SET done_points = (SELECT COUNT(*) FROM results WHERE {self._committed}), "
                    f"failed_points = (SELECT COUNT(*) FROM results WHERE {self._committed} AND status = 'failed'), "
                    f"updated_at = {self.dialect.now_text} WHERE id = ?",
                    (row["sweep_id"], row["sweep_id"], row["sweep_id"]),
                )
            return rid

    def get_result(self, result_id: int) -> ResultRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM results WHERE id = ?", (result_id,)).fetchone()
            return _record(row) if row else None

    def results_by_id(self, result_ids: list[int]) -> dict[int, ResultRecord]:
        """The result rows of these ids (ids with no row left out), in one query."""
        ids = sorted({int(i) for i in result_ids})
        if not ids:
            return {}
        with self.connect() as conn:
            return {
                r["id"]: _record(r)
                for r in conn.execute(f"SELECT * FROM results WHERE id IN ({', '.join('?' for _ in ids)})", ids)
            }

    def set_result_recording(self, result_id: int, record: dict[str, Any]) -> None:
        """What became of the result's raw recording (service/store/recordings.py)."""
        _update(self, "results", result_id, {"recording": record})

    def mark_recordings_deleted(self, result_ids: list[int], reason: str) -> None:
        """Their recordings were deleted (retention): the results say so, and when."""
        with self.transaction() as conn:
            conn.executemany(
                f"UPDATE results SET recording_json = {self.dialect.json_set_text('recording_json', 'deleted')} "
                "WHERE id = ? AND recording_json IS NOT NULL",
                [(reason, rid) for rid in result_ids],
            )

    def sweep_results(self, sweep_id: int) -> list[ResultRecord]:
        """The sweep's current results: one per operating point measured (earlier attempts left out)."""
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT * FROM results WHERE sweep_id = ? AND superseded_by IS NULL ORDER BY id", (sweep_id,)
                )
            ]

    def sweep_outcome(self, sweep_id: int) -> dict[str, Any]:
        """Counts of the sweep's current results per status, and their total plant time (s)."""
        with self.connect() as conn:
            rows = conn.execute(
                "SELECT status, COUNT(*) AS n, SUM(plant_time_s) AS plant FROM results "
                "WHERE sweep_id = ? AND superseded_by IS NULL GROUP BY status",
                (sweep_id,),
            ).fetchall()
        counts = {status: 0 for status in ("ok", "below_target", "no_authority", "failed")}
        counts.update({r["status"]: r["n"] for r in rows})
        return {"counts": counts, "plant_time_s": float(sum(r["plant"] or 0.0 for r in rows))}

    def sweep_result_history(self, sweep_id: int) -> list[ResultRecord]:
        """Every attempt of the sweep, superseded ones included, oldest first."""
        with self.connect() as conn:
            return [
                _record(r) for r in conn.execute("SELECT * FROM results WHERE sweep_id = ? ORDER BY id", (sweep_id,))
            ]

    def committed_points(self, sweep_id: int) -> set[tuple[float, float, float]]:
        """Operating points whose current result counts (a run an interlock discarded does not):
        a resumed sweep measures only the others."""
        with self.connect() as conn:
            return {
                (r["torque_nm"], r["speed_rpm"], r["udc_v"])
                for r in conn.execute(
                    f"SELECT torque_nm, speed_rpm, udc_v FROM results WHERE {self._committed}", (sweep_id,)
                )
            }

    # --- maps --------------------------------------------------------------------------------------
    def create_map(
        self,
        sweep_id: int | None,
        harmonic_order: int,
        method: str,
        axes: dict[str, Any],
        cells: list[tuple[int | None, float, float, float]],
        bench_identity: str,
        software_version: str,
        fills: dict[tuple[float, float, float], Any] | None = None,
        refined_from: int | None = None,
        provenance: dict[str, Any] | None = None,
    ) -> int:
        """A map of `cells` [(result_id, torque, speed, udc)]; `fills` {(torque, speed, udc): Fill} the
        fill rule's entries for cells that are not ok (service/maps/fill.py)."""
        fills = fills or {}
        with self.transaction() as conn:
            map_id = _new_id(
                conn.execute(
                    "INSERT INTO maps (sweep_id, harmonic_order, method, axes_json, bench_identity, software_version, "
                    "created_at, refined_from, provenance_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        sweep_id,
                        harmonic_order,
                        method,
                        json.dumps(axes),
                        bench_identity,
                        software_version,
                        now_iso(),
                        refined_from,
                        json.dumps(provenance) if provenance is not None else None,
                    ),
                )
            )
            rows = []
            for result_id, t, n, u in cells:
                fill = fills.get((t, n, u))
                rows.append(
                    (
                        map_id,
                        result_id,
                        t,
                        n,
                        u,
                        fill.theta_cos if fill else None,
                        fill.theta_sin if fill else None,
                        fill.source if fill else None,
                    )
                )
            conn.executemany(
                "INSERT INTO map_cells (map_id, result_id, torque_nm, speed_rpm, udc_v, fill_theta_cos, "
                "fill_theta_sin, fill_source) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                rows,
            )
            if sweep_id is not None:
                conn.execute("UPDATE sweeps SET map_id = ? WHERE id = ?", (map_id, sweep_id))
            return map_id

    def get_map(self, map_id: int) -> MapRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM maps WHERE id = ?", (map_id,)).fetchone()
            if not row:
                return None
            cells = conn.execute(
                "SELECT c.torque_nm, c.speed_rpm, c.udc_v, r.id AS result_id, r.status, r.theta_cos, r.theta_sin, "
                "r.gamma_deg, r.delta_deg, r.suppression_db, r.target_db, r.noise_floor_db, r.error, c.fill_theta_cos, "
                "c.fill_theta_sin, c.fill_source FROM map_cells c LEFT JOIN results r ON r.id = c.result_id "
                "WHERE c.map_id = ? ORDER BY c.udc_v, c.speed_rpm, c.torque_nm",
                (map_id,),
            ).fetchall()
            return cast(MapRecord, {**_record(row), "cells": [_record(c) for c in cells]})

    def list_maps(self, limit: int = 100) -> list[MapSummaryRecord]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT id, sweep_id, harmonic_order, method, created_at FROM maps ORDER BY id DESC LIMIT ?",
                    (limit,),
                )
            ]

    # --- map validations (the LUT measured in the drive's LUT mode) ---------------------------------
    def insert_validation(self, row: dict[str, Any]) -> int:
        with self.transaction() as conn:
            return _insert(conn, "map_validations", row)

    def update_validation(self, validation_id: int, **fields: Any) -> None:
        _update(self, "map_validations", validation_id, fields)

    def latest_validation(self, map_id: int) -> ValidationRecord | None:
        with self.connect() as conn:
            row = conn.execute(
                "SELECT * FROM map_validations WHERE map_id = ? ORDER BY id DESC LIMIT 1", (map_id,)
            ).fetchone()
            return _record(row) if row else None

    def validation_of_job(self, job_id: int) -> ValidationRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM map_validations WHERE job_id = ?", (job_id,)).fetchone()
            return _record(row) if row else None

    # --- schedules ---------------------------------------------------------------------------------
    def create_schedule(
        self,
        name: str,
        cron: str,
        timezone_name: str,
        sweep: dict[str, Any],
        enabled: bool,
        now_utc: str,
        bench: str | None = None,
    ) -> int:
        with self.transaction() as conn:
            return _new_id(
                conn.execute(
                    "INSERT INTO schedules (name, cron, timezone, sweep_json, enabled, created_at, updated_at, last_due_at, "
                    "bench) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (name, cron, timezone_name, json.dumps(sweep), int(enabled), now_utc, now_utc, now_utc, bench),
                )
            )

    def update_schedule(self, schedule_id: int, **fields: Any) -> None:
        _update(self, "schedules", schedule_id, fields)

    def get_schedule(self, schedule_id: int) -> ScheduleRecord | None:
        """A schedule that has not been deleted."""
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM schedules WHERE id = ? AND deleted_at IS NULL", (schedule_id,)).fetchone()
            return _record(row) if row else None

    def schedule_named(self, name: str) -> ScheduleRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM schedules WHERE name = ? AND deleted_at IS NULL", (name,)).fetchone()
            return _record(row) if row else None

    def list_schedules(self, limit: int = 1000) -> list[ScheduleRecord]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute("SELECT * FROM schedules WHERE deleted_at IS NULL ORDER BY id LIMIT ?", (limit,))
            ]

    def insert_schedule_run(
        self,
        schedule_id: int,
        due_at: str,
        fired_at: str,
        outcome: str,
        sweep_id: int | None = None,
        note: str | None = None,
    ) -> int:
        with self.transaction() as conn:
            return _new_id(
                conn.execute(
                    "INSERT INTO schedule_runs (schedule_id, due_at, fired_at, outcome, sweep_id, note) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule_id, due_at, fired_at, outcome, sweep_id, note),
                )
            )

    def schedule_runs(self, schedule_id: int, limit: int = 20) -> list[ScheduleRunRecord]:
        """The schedule's most recent runs, newest first, with the state of the sweep each submitted."""
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT r.*, s.state AS sweep_state FROM schedule_runs r LEFT JOIN sweeps s ON s.id = r.sweep_id "
                    "WHERE r.schedule_id = ? ORDER BY r.id DESC LIMIT ?",
                    (schedule_id, limit),
                )
            ]

    def pending_schedule_sweep(self, schedule_id: int) -> int | None:
        """A sweep of this schedule still waiting for the bench (queued, never started), if any."""
        with self.connect() as conn:
            row = conn.execute(
                "SELECT id FROM sweeps WHERE schedule_id = ? AND state = 'queued' AND started_at IS NULL "
                "ORDER BY id LIMIT 1",
                (schedule_id,),
            ).fetchone()
            return row["id"] if row else None

    # --- a lab: benches, their heartbeat, and the jobs each bench's service claims (issue 20) ---------------
    # Portable SQL only (SQLite and PostgreSQL): `?` placeholders, INSERT ... ON CONFLICT, RETURNING.
    # Liveness is on the database's clock (issue 25): a heartbeat is stamped, and its age judged, by the
    # database, never by a bench PC's clock, which may be off by any amount.
    def claim_bench(self, bench: dict[str, Any], stale_s: float) -> dict[str, Any] | None:
        """Take the bench name for `bench["instance"]` in one statement: inserted, or taken over if the row
        is this instance's, stopped, or proven stale: its heartbeat older than `stale_s` by the database's
        clock. None: claimed; else the row of the instance that holds it (get_bench's, with `seen_s`)."""
        row = {**bench, "state": "starting", "busy": 0, "running": None, "stopped_at": None}
        columns = list(row)
        values = ["?" for _ in columns] + [self.dialect.now_text] * 2
        columns += ["started_at", "last_seen"]
        updates = ", ".join(f"{c} = excluded.{c}" for c in columns if c != "name")
        with self.transaction() as conn:
            taken = conn.execute(
                f"INSERT INTO benches ({', '.join(columns)}) VALUES ({', '.join(values)}) "
                f"ON CONFLICT (name) DO UPDATE SET {updates} WHERE benches.instance = excluded.instance "
                f"OR benches.stopped_at IS NOT NULL OR {self.dialect.seconds_since('benches.last_seen')} > ? "
                "RETURNING instance",
                (*row.values(), stale_s),
            ).fetchone()
            if taken is not None:
                return None
            return self._bench_row(conn, bench["name"])

    def bench_heartbeat(self, name: str, instance: str, state: str, busy: bool, running: str | None) -> bool:
        """Renew the bench's row (stamped by the database's clock); False: another instance has taken the
        name over."""
        with self.transaction() as conn:
            cur = conn.execute(
                f"UPDATE benches SET state = ?, busy = ?, running = ?, last_seen = {self.dialect.now_text} "
                "WHERE name = ? AND instance = ?",
                (state, int(busy), running, name, instance),
            )
            return _one_row(cur)

    def bench_stopped(self, name: str, instance: str) -> None:
        """An orderly stop: the row says stopped (the name is free at once)."""
        now = self.dialect.now_text
        with self.transaction() as conn:
            conn.execute(
                f"UPDATE benches SET state = 'stopped', busy = 0, running = NULL, last_seen = {now}, stopped_at = {now} "
                "WHERE name = ? AND instance = ?",
                (name, instance),
            )

    def get_bench(self, name: str) -> dict[str, Any] | None:
        """The bench's row with `seen_s`: the age of its last heartbeat by the database's clock."""
        with self.connect() as conn:
            return self._bench_row(conn, name)

    def list_benches(self) -> list[dict[str, Any]]:
        """Every bench's row, each with `seen_s` as get_bench's."""
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    f"SELECT *, {self.dialect.seconds_since('last_seen')} AS seen_s FROM benches ORDER BY name"
                )
            ]

    def _bench_row(self, conn: Any, name: str) -> dict[str, Any] | None:
        row = conn.execute(
            f"SELECT *, {self.dialect.seconds_since('last_seen')} AS seen_s FROM benches WHERE name = ?", (name,)
        ).fetchone()
        return _record(row) if row else None

    def queued_per_bench(self) -> dict[str, int]:
        """Jobs waiting for each bench (a paused sweep's parked job does not count)."""
        with self.connect() as conn:
            return {
                r["bench"]: r["n"]
                for r in conn.execute(
                    "SELECT j.bench AS bench, COUNT(*) AS n FROM jobs j "
                    f"WHERE j.state = 'queued' AND j.bench IS NOT NULL AND {_NOT_PARKED} GROUP BY j.bench"
                )
            }

    def bench_busy(self, bench: str) -> bool:
        """A job of this bench queued or running: a new sweep for it would wait. The job of a paused sweep
        is parked (queued, but no service takes it: the bench is free) and does not count."""
        with self.connect() as conn:
            return (
                conn.execute(
                    "SELECT 1 FROM jobs j WHERE j.bench = ? AND "
                    f"(j.state = 'running' OR (j.state = 'queued' AND {_NOT_PARKED})) LIMIT 1",
                    (bench,),
                ).fetchone()
                is not None
            )

    def claim_job(self, bench: str, instance: str, job_id: int | None = None) -> int | None:
        """Take the next job of `bench` (oldest first) for `instance`, queued -> running in one statement:
        one waiting for any service of the bench (claimed_by NULL) or queued by this instance (its own, or
        its paused sweep's job queued again). A paused sweep's job waits. `job_id`: only that job, and
        only if this instance queued it (a CLI run takes only what it queued). None: nothing to take."""
        now = now_iso()
        if job_id is not None:
            pick = "SELECT id FROM jobs WHERE id = ? AND bench = ? AND state = 'queued' AND claimed_by = ?"
            args = [job_id, bench, instance]
        else:
            pick = (
                "SELECT j.id FROM jobs j WHERE j.bench = ? AND j.state = 'queued' "
                f"AND (j.claimed_by IS NULL OR j.claimed_by = ?) AND {_NOT_PARKED} "
                "ORDER BY j.id LIMIT 1"
            )
            args = [bench, instance]
        # a read first: the worker polls twice a second, and an idle bench must not take the write lock each time
        with self.connect() as conn:
            if conn.execute(pick, args).fetchone() is None:
                return None
        with self.transaction() as conn:
            row = conn.execute(
                f"UPDATE jobs SET state = 'running', claimed_by = ?, started_at = ?, updated_at = {self.dialect.now_text} "
                # the dialect's row locking: none on SQLite (one writer at a time), FOR UPDATE SKIP LOCKED on
                # PostgreSQL (two claims never wait on, or take, the same row)
                f"WHERE id = ({pick} {self.dialect.skip_locked}) AND state = 'queued' RETURNING id",
                (instance, now, *args),
            ).fetchone()
            return row["id"] if row else None

    def cancel_queued_job(self, job_id: int) -> bool:
        """Cancel a job no service has taken yet (another bench's): False if it was taken first."""
        now = now_iso()
        with self.transaction() as conn:
            row = conn.execute(
                f"UPDATE jobs SET state = 'cancelled', finished_at = ?, updated_at = {self.dialect.now_text} "
                "WHERE id = ? AND state = 'queued' RETURNING id",
                (now, job_id),
            ).fetchone()
            return row is not None

    def cancel_waiting_sweep(self, sweep_id: int) -> bool:
        """Cancel a queued sweep whose job no service has taken yet (another bench's), job and sweep in one
        transaction: False if its bench's service took it first."""
        now = now_iso()
        with self.transaction() as conn:
            job = conn.execute(
                f"UPDATE jobs SET state = 'cancelled', finished_at = ?, updated_at = {self.dialect.now_text} "
                "WHERE sweep_id = ? AND state = 'queued' AND claimed_by IS NULL RETURNING id",
                (now, sweep_id),
            ).fetchone()
            if job is None:
                return False
            conn.execute(
                f"UPDATE sweeps SET state = 'cancelled', finished_at = ?, updated_at = {self.dialect.now_text} "
                "WHERE id = ? AND state = 'queued'",
                (now, sweep_id),
            )
            return True

    def request_sweep_control(self, sweep_id: int, action: str) -> None:
        """Ask the sweep's bench's service to pause, resume or cancel it (it acts within about a second)."""
        with self.transaction() as conn:
            conn.execute(
                f"UPDATE sweeps SET control_request = ?, control_note = NULL, updated_at = {self.dialect.now_text} "
                "WHERE id = ?",
                (action, sweep_id),
            )

    def sweep_control_requests(self, bench: str) -> list[tuple[int, str]]:
        """[(sweep id, action)] asked at other services for this bench's sweeps."""
        with self.connect() as conn:
            return [
                (r["id"], r["control_request"])
                for r in conn.execute(
                    "SELECT id, control_request FROM sweeps WHERE bench = ? AND control_request IS NOT NULL "
                    "ORDER BY id",
                    (bench,),
                )
            ]

    def take_sweep_control(self, sweep_id: int, action: str) -> bool:
        """Take a control request (cleared in the same write): False if it changed or was taken meanwhile."""
        with self.transaction() as conn:
            row = conn.execute(
                "UPDATE sweeps SET control_request = NULL WHERE id = ? AND control_request = ? RETURNING id",
                (sweep_id, action),
            ).fetchone()
            return row is not None

    def bench_unfinished_jobs(self, bench: str) -> list[JobRecord]:
        """This bench's jobs left queued or running, and those of no bench (from before benches: one
        database, one bench)."""
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT * FROM jobs WHERE state IN ('queued', 'running') AND (bench = ? OR bench IS NULL) "
                    "ORDER BY id",
                    (bench,),
                )
            ]

    def bench_unfinished_sweeps(self, bench: str) -> list[SweepRecord]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT * FROM sweeps WHERE state IN ('queued', 'running', 'paused', 'interrupted') "
                    "AND (bench = ? OR bench IS NULL) ORDER BY id",
                    (bench,),
                )
            ]

    def bench_running_validations(self, bench: str) -> list[ValidationRecord]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT v.* FROM map_validations v LEFT JOIN jobs j ON j.id = v.job_id WHERE v.state = 'running' "
                    "AND (j.bench = ? OR j.bench IS NULL)",
                    (bench,),
                )
            ]

    def adopt_unnamed_rows(self, bench: str) -> None:
        """Rows from before benches (bench NULL) become this bench's: that database served one bench."""
        with self.transaction() as conn:
            for table in ("jobs", "sweeps", "schedules"):
                conn.execute(f"UPDATE {table} SET bench = ? WHERE bench IS NULL", (bench,))

    def database_now(self) -> str:
        """The database's clock as UTC ISO text: the lab's one clock, that updated_at and heartbeats use."""
        with self.connect() as conn:
            now: str = conn.execute(f"SELECT {self.dialect.now_text}").fetchone()[0]
            return now

    def changed_since(self, since: str) -> tuple[list[JobRecord], list[SweepRecord]]:
        """Jobs and sweeps written at or after `since` (UTC ISO on the database's clock), oldest write first."""
        with self.connect() as conn:
            jobs = [
                _record(r)
                for r in conn.execute("SELECT * FROM jobs WHERE updated_at >= ? ORDER BY updated_at, id", (since,))
            ]
            sweeps = [
                _record(r)
                for r in conn.execute("SELECT * FROM sweeps WHERE updated_at >= ? ORDER BY updated_at, id", (since,))
            ]
            return jobs, sweeps


# a job `j` that is not a paused sweep's: that job is parked (queued, but no service takes it until resume)
_NOT_PARKED = "NOT EXISTS (SELECT 1 FROM sweeps s WHERE s.id = j.sweep_id AND s.state = 'paused')"

_IDENT = re.compile(r"^[a-z_]+$")


def _check_columns(fields: dict[str, Any]) -> None:
    for key in fields:
        if not _IDENT.match(key):
            raise StorageError(f"bad column name {key!r}")


# the columns that hold JSON, per table: a record names them without the suffix, decoded
# (results.detail_json -> record["detail"]); a write may give them either way (decoded is encoded here)
JSON_COLUMNS = {
    "jobs": ("request",),
    "sweeps": ("grid", "options", "refinement"),
    "results": ("options", "detail", "traces", "recording"),
    "maps": ("axes", "provenance"),
    "map_validations": ("options", "summary", "cells", "download"),
    "schedules": ("sweep",),
}


def _record(row: Any) -> Any:
    """A row as the layers above read it (service/store/records.py): every `x_json` column decoded as `x`.
    Typed by the caller's return, its table's record (tests/unit/test_records_schema.py holds them equal)."""
    record: dict[str, Any] = {}
    for key in row.keys():
        value = row[key]
        if key.endswith("_json"):
            record[key[:-5]] = json.loads(value) if value is not None else None
        else:
            record[key] = value
    return record


def encode_columns(table: str, fields: dict[str, Any]) -> dict[str, Any]:
    """{column: value} of a write: decoded JSON fields encoded into their `x_json` columns."""
    names = JSON_COLUMNS.get(table, ())
    return {
        (f"{k}_json" if k in names else k): (json.dumps(v) if k in names and v is not None else v)
        for k, v in fields.items()
    }


def _new_id(cursor: Any) -> int:
    """The id of the row an INSERT made (sqlite3's lastrowid; the PostgreSQL engine's RETURNING id)."""
    new_id: int = cursor.lastrowid
    return new_id


def _one_row(cursor: Any) -> bool:
    """An UPDATE or DELETE touched exactly one row."""
    rowcount: int = cursor.rowcount
    return rowcount == 1


def _insert(conn: Any, table: str, row: dict[str, Any]) -> int:
    """One row from a {column: value} dict, in the caller's transaction; its id."""
    row = encode_columns(table, row)
    _check_columns(row)
    marks = ", ".join("?" for _ in row)
    return _new_id(conn.execute(f"INSERT INTO {table} ({', '.join(row)}) VALUES ({marks})", tuple(row.values())))


# tables whose every write sets updated_at, on the database's clock (the one clock of a lab: a bench PC's
# may be off): another bench's service shows their progress from it (service/runs/lab.py LabWatch)
_TRACKED = ("jobs", "sweeps")


def _update(storage: Storage, table: str, row_id: int, fields: dict[str, Any]) -> None:
    if not fields:
        return
    fields = encode_columns(table, fields)
    _check_columns(fields)
    sets = ", ".join(f"{k} = ?" for k in fields)
    if table in _TRACKED and "updated_at" not in fields:
        sets += f", updated_at = {storage.dialect.now_text}"
    with storage.transaction() as conn:
        conn.execute(f"UPDATE {table} SET {sets} WHERE id = ?", (*fields.values(), row_id))


def _sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()
