"""SQLite storage: numbered migrations (migrations/NNNN_*.sql, PRAGMA user_version) and the
repository functions the service uses. One connection per call, WAL mode, every write in one
transaction, so a failure in one operating point never touches the results of others."""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import secrets
import sqlite3
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

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

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"
_MIGRATION_NAME = re.compile(r"^(\d{4})_[a-z0-9_]+\.sql$")


class StorageError(RuntimeError):
    pass


class StorageUnavailable(StorageError):
    """The database cannot be used now, for a reason that passes (another process holds its lock, its
    filesystem is read-only or full, an I/O error): what needs it waits and tries again; the API answers
    503 with Retry-After. str() names the cause and the file (for the log); `public` names the file
    without the server's path to it (for answers and a sweep's pause reason)."""

    def __init__(self, cause: str, message: str, retry_after_s: float = 5.0, public: str | None = None):
        super().__init__(message)
        self.cause = cause
        self.retry_after_s = retry_after_s
        self.public = public if public is not None else message


# sqlite3's OperationalError texts of the causes that pass, and what to tell the operator
_UNAVAILABLE = (
    ("database is locked", "locked", "another process holds its lock"),
    ("readonly database", "read_only", "its filesystem is read-only"),
    ("read-only", "read_only", "its filesystem is read-only"),
    ("database or disk is full", "disk_full", "its disk is full"),
    ("disk i/o error", "io_error", "a disk I/O error"),
    ("unable to open database file", "cannot_open", "the file cannot be opened"),
)


def unavailable(exc: BaseException, path: Path) -> StorageUnavailable | None:
    """The StorageUnavailable a sqlite3 error stands for (None: not one that passes)."""
    if not isinstance(exc, sqlite3.OperationalError):
        return None
    text = str(exc).lower()
    for needle, cause, what in _UNAVAILABLE:
        if needle in text:
            return StorageUnavailable(
                cause, f"database {path}: {what} ({exc})", public=f"database {path.name}: {what} ({exc})"
            )
    return None


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def migrations(directory: Path = MIGRATIONS_DIR) -> list[tuple[int, Path]]:
    found = []
    for path in sorted(directory.glob("*.sql")):
        m = _MIGRATION_NAME.match(path.name)
        if not m:
            raise StorageError(f"migration file {path.name} is not named NNNN_description.sql")
        found.append((int(m.group(1)), path))
    numbers = [n for n, _ in found]
    if numbers != list(range(1, len(found) + 1)):
        raise StorageError(f"migrations must be numbered 1..N without gaps, found {numbers}")
    return found


class Storage:
    def __init__(self, path: str | Path, busy_timeout_s: float = 10.0):
        self.path = Path(path)
        self.busy_timeout_s = busy_timeout_s  # sqlite3 waits this long for another process's lock before it says so
        self._known_tokens: dict[
            str, str
        ] = {}  # sha256 -> role of tokens seen valid (used while the database is unavailable)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._write_lock = threading.Lock()
        self.migrate()

    @contextlib.contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        """A connection; a sqlite3 error that passes (lock, read-only or full filesystem) becomes
        StorageUnavailable, here and in the caller's use of the connection."""
        conn = None
        try:
            conn = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute("PRAGMA journal_mode = WAL")
            yield conn
        except sqlite3.Error as exc:
            passing = unavailable(exc, self.path)
            if passing is not None:
                raise passing from exc
            raise
        finally:
            if conn is not None:
                conn.close()

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._write_lock, self.connect() as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                with contextlib.suppress(sqlite3.Error):  # a full disk or I/O error may have rolled it back already
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def migrate(self) -> int:
        with self._write_lock, self.connect() as conn:
            current = conn.execute("PRAGMA user_version").fetchone()[0]
            available = migrations()
            if current > len(available):
                raise StorageError(
                    f"database {self.path} is at schema {current}, newer than this software ({len(available)})"
                )
            # SQLite's procedure for a table rebuild (a changed CHECK): foreign keys off outside the
            # transaction, checked inside it before the commit
            conn.execute("PRAGMA foreign_keys = OFF")
            try:
                for number, path in available[current:]:
                    conn.execute("BEGIN IMMEDIATE")
                    try:
                        for statement in _split_sql(path.read_text()):
                            conn.execute(statement)
                        broken = conn.execute("PRAGMA foreign_key_check").fetchall()
                        if broken:
                            raise StorageError(f"{len(broken)} foreign key violation(s), first in table {broken[0][0]}")
                        conn.execute(f"PRAGMA user_version = {number}")
                        conn.execute("COMMIT")
                    except Exception as exc:
                        conn.execute("ROLLBACK")
                        raise StorageError(f"migration {path.name} failed: {exc}") from exc
            finally:
                conn.execute("PRAGMA foreign_keys = ON")
            return conn.execute("PRAGMA user_version").fetchone()[0]

    # --- tokens ------------------------------------------------------------------------------------
    def create_token(self, role: str, label: str = "") -> tuple[int, str]:
        token = "rc_" + secrets.token_urlsafe(32)
        with self.transaction() as conn:
            cur = conn.execute(
                "INSERT INTO api_tokens (role, token_sha256, label, created_at) VALUES (?, ?, ?, ?)",
                (role, _sha256(token), label, now_iso()),
            )
            return cur.lastrowid, token

    def revoke_token(self, token_id: int) -> bool:
        with self.transaction() as conn:
            cur = conn.execute(
                "UPDATE api_tokens SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL", (now_iso(), token_id)
            )
            return cur.rowcount == 1

    def token_role(self, token: str) -> str | None:
        """The token's role (None: unknown or revoked). While the database is unavailable, a token this
        process has seen valid before stays valid (an operator can still cancel or pause; revoking one
        needs the database anyway)."""
        digest = _sha256(token)
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

    def list_tokens(self) -> list[dict]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute("SELECT id, role, label, created_at, revoked_at FROM api_tokens ORDER BY id")
            ]

    # --- jobs --------------------------------------------------------------------------------------
    def create_job(self, kind: str, request: dict, sweep_id: int | None = None) -> int:
        with self.transaction() as conn:
            return conn.execute(
                "INSERT INTO jobs (kind, state, request_json, sweep_id, created_at) VALUES (?, 'queued', ?, ?, ?)",
                (kind, json.dumps(request), sweep_id, now_iso()),
            ).lastrowid

    def update_job(self, job_id: int, **fields: Any) -> None:
        _update(self, "jobs", job_id, fields)

    def get_job(self, job_id: int) -> JobRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            return _record(row) if row else None

    def list_jobs(self, limit: int = 100) -> list[JobRecord]:
        with self.connect() as conn:
            return [_record(r) for r in conn.execute("SELECT * FROM jobs ORDER BY id DESC LIMIT ?", (limit,))]

    def unfinished_jobs(self) -> list[JobRecord]:
        """Jobs left queued or running (on start-up: by a previous process)."""
        with self.connect() as conn:
            return [
                _record(r) for r in conn.execute("SELECT * FROM jobs WHERE state IN ('queued', 'running') ORDER BY id")
            ]

    # --- sweeps ------------------------------------------------------------------------------------
    def create_sweep(
        self,
        method: str,
        harmonic_order: int,
        grid: dict,
        options: dict,
        total: int,
        bench_identity: str,
        software_version: str,
        schedule_id: int | None = None,
        kind: str = "sweep",
        source_map_id: int | None = None,
        refinement: dict | None = None,
    ) -> int:
        """A sweep, or (kind `refinement`) a map's refinement: its state in `refinement` (service/runs/refinement.py)."""
        with self.transaction() as conn:
            return conn.execute(
                "INSERT INTO sweeps (state, method, harmonic_order, grid_json, options_json, total_points, bench_identity, "
                "software_version, created_at, schedule_id, kind, source_map_id, refinement_json) "
                "VALUES ('queued', ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
                ),
            ).lastrowid

    def update_sweep(self, sweep_id: int, **fields: Any) -> None:
        _update(self, "sweeps", sweep_id, fields)

    def get_sweep(self, sweep_id: int) -> SweepRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM sweeps WHERE id = ?", (sweep_id,)).fetchone()
            return _record(row) if row else None

    def unfinished_sweeps(self) -> list[SweepRecord]:
        with self.connect() as conn:
            return [
                _record(r)
                for r in conn.execute(
                    "SELECT * FROM sweeps WHERE state IN ('queued', 'running', 'paused', 'interrupted') ORDER BY id"
                )
            ]

    def list_sweeps(self, limit: int = 100) -> list[SweepRecord]:
        with self.connect() as conn:
            return [_record(r) for r in conn.execute("SELECT * FROM sweeps ORDER BY id DESC LIMIT ?", (limit,))]

    # --- results -----------------------------------------------------------------------------------
    def insert_result(self, row: dict) -> int:
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
                    f"UPDATE sweeps SET done_points = (SELECT COUNT(*) FROM results WHERE {_COMMITTED}), "
                    f"failed_points = (SELECT COUNT(*) FROM results WHERE {_COMMITTED} AND status = 'failed') "
                    "WHERE id = ?",
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

    def set_result_recording(self, result_id: int, record: dict) -> None:
        """What became of the result's raw recording (service/store/recordings.py)."""
        _update(self, "results", result_id, {"recording": record})

    def mark_recordings_deleted(self, result_ids: list[int], reason: str) -> None:
        """Their recordings were deleted (retention): the results say so, and when."""
        with self.transaction() as conn:
            conn.executemany(
                "UPDATE results SET recording_json = json_set(recording_json, '$.deleted', ?) "
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

    def sweep_outcome(self, sweep_id: int) -> dict:
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
                    f"SELECT torque_nm, speed_rpm, udc_v FROM results WHERE {_COMMITTED}", (sweep_id,)
                )
            }

    # --- maps --------------------------------------------------------------------------------------
    def create_map(
        self,
        sweep_id: int | None,
        harmonic_order: int,
        method: str,
        axes: dict,
        cells: list[tuple[int | None, float, float, float]],
        bench_identity: str,
        software_version: str,
        fills: dict | None = None,
        refined_from: int | None = None,
        provenance: dict | None = None,
    ) -> int:
        """A map of `cells` [(result_id, torque, speed, udc)]; `fills` {(torque, speed, udc): Fill} the
        fill rule's entries for cells that are not ok (service/maps/fill.py)."""
        fills = fills or {}
        with self.transaction() as conn:
            map_id = conn.execute(
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
            ).lastrowid
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
            return {**_record(row), "cells": [_record(c) for c in cells]}

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
    def insert_validation(self, row: dict) -> int:
        with self.transaction() as conn:
            return _insert(conn, "map_validations", row)

    def update_validation(self, validation_id: int, **fields: Any) -> None:
        _update(self, "map_validations", validation_id, fields)

    def running_validations(self) -> list[ValidationRecord]:
        with self.connect() as conn:
            return [_record(r) for r in conn.execute("SELECT * FROM map_validations WHERE state = 'running'")]

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
        self, name: str, cron: str, timezone_name: str, sweep: dict, enabled: bool, now_utc: str
    ) -> int:
        with self.transaction() as conn:
            return conn.execute(
                "INSERT INTO schedules (name, cron, timezone, sweep_json, enabled, created_at, updated_at, last_due_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (name, cron, timezone_name, json.dumps(sweep), int(enabled), now_utc, now_utc, now_utc),
            ).lastrowid

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
            return conn.execute(
                "INSERT INTO schedule_runs (schedule_id, due_at, fired_at, outcome, sweep_id, note) VALUES (?, ?, ?, ?, ?, ?)",
                (schedule_id, due_at, fired_at, outcome, sweep_id, note),
            ).lastrowid

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

    def bench_has_work(self) -> bool:
        """A job queued or running: a new sweep would wait for the bench. The job of a paused sweep is
        parked (queued, out of the worker's queue: the bench is free) and does not count."""
        with self.connect() as conn:
            return (
                conn.execute(
                    "SELECT 1 FROM jobs j LEFT JOIN sweeps s ON s.id = j.sweep_id WHERE j.state = 'running' "
                    "OR (j.state = 'queued' AND (s.state IS NULL OR s.state != 'paused')) LIMIT 1"
                ).fetchone()
                is not None
            )


_IDENT = re.compile(r"^[a-z_]+$")

# a sweep's committed results: current (not superseded) and not discarded by an interlock
# (detail_json "discarded" names why; the attempt stays as history and the point is measured again)
_COMMITTED = "sweep_id = ? AND superseded_by IS NULL AND json_extract(detail_json, '$.discarded') IS NULL"


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


def _record(row: sqlite3.Row) -> dict[str, Any]:
    """A row as the layers above read it (service/store/records.py): every `x_json` column decoded as `x`."""
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


def _insert(conn: sqlite3.Connection, table: str, row: dict[str, Any]) -> int:
    """One row from a {column: value} dict, in the caller's transaction; its id."""
    row = encode_columns(table, row)
    _check_columns(row)
    marks = ", ".join("?" for _ in row)
    return conn.execute(f"INSERT INTO {table} ({', '.join(row)}) VALUES ({marks})", tuple(row.values())).lastrowid


def _update(storage: Storage, table: str, row_id: int, fields: dict[str, Any]) -> None:
    if not fields:
        return
    fields = encode_columns(table, fields)
    _check_columns(fields)
    sets = ", ".join(f"{k} = ?" for k in fields)
    with storage.transaction() as conn:
        conn.execute(f"UPDATE {table} SET {sets} WHERE id = ?", (*fields.values(), row_id))


def _sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _split_sql(script: str) -> list[str]:
    """Statements of a migration script (no semicolons inside our literals; comments stripped)."""
    lines = [line.split("--", 1)[0] for line in script.splitlines()]
    return [stmt.strip() for stmt in "\n".join(lines).split(";") if stmt.strip()]
