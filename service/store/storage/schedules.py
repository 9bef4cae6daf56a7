"""Schedules (table schedules) and their runs (table schedule_runs: each time one came due, and what
it did)."""

from __future__ import annotations

import json
from typing import Any

from service.store.records import ScheduleRecord, ScheduleRunRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, new_id


class ScheduleStore(Database):
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
            return new_id(
                conn.execute(
                    "INSERT INTO schedules (name, cron, timezone, sweep_json, enabled, created_at, updated_at, last_due_at, "
                    "bench) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (name, cron, timezone_name, json.dumps(sweep), int(enabled), now_utc, now_utc, now_utc, bench),
                )
            )

    def update_schedule(self, schedule_id: int, **fields: Any) -> None:
        self._update_row("schedules", schedule_id, fields)

    def get_schedule(self, schedule_id: int) -> ScheduleRecord | None:
        """A schedule that has not been deleted."""
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM schedules WHERE id = ? AND deleted_at IS NULL", (schedule_id,)).fetchone()
            return as_record(row) if row else None

    def schedule_named(self, name: str) -> ScheduleRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM schedules WHERE name = ? AND deleted_at IS NULL", (name,)).fetchone()
            return as_record(row) if row else None

    def list_schedules(self, limit: int = 1000) -> list[ScheduleRecord]:
        with self.connect() as conn:
            return [
                as_record(r)
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
            return new_id(
                conn.execute(
                    "INSERT INTO schedule_runs (schedule_id, due_at, fired_at, outcome, sweep_id, note) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule_id, due_at, fired_at, outcome, sweep_id, note),
                )
            )

    def schedule_runs(self, schedule_id: int, limit: int = 20) -> list[ScheduleRunRecord]:
        """The schedule's most recent runs, newest first, with the state of the sweep each submitted."""
        with self.connect() as conn:
            return [
                as_record(r)
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
