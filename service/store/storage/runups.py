"""Run-ups (table runups: one row per run-up job, its request and its order analysis as measured)."""

from __future__ import annotations

from typing import Any

from service.store.records import RunupRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, insert_row


class RunupStore(Database):
    def insert_runup(self, row: dict[str, Any]) -> int:
        with self.transaction() as conn:
            return insert_row(conn, "runups", row)

    def runup_of_job(self, job_id: int) -> RunupRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM runups WHERE job_id = ? ORDER BY id DESC LIMIT 1", (job_id,)).fetchone()
            return as_record(row) if row else None

    def set_runup_recording(self, runup_id: int, record: dict[str, Any]) -> None:
        self._update_row("runups", runup_id, {"recording": record})
