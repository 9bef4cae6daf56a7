"""Jobs (table jobs), each one run of a job kind on one bench: their rows, the queue every bench's
service takes its next job from (claim_job: queued -> running in one statement, on either engine), and
what a bench left unfinished."""

from __future__ import annotations

import json
from typing import Any

from service.store.records import JobRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, new_id, now_iso

# a job `j` that is not a paused sweep's: that job is parked (queued, but no service takes it until resume)
_NOT_PARKED = "NOT EXISTS (SELECT 1 FROM sweeps s WHERE s.id = j.sweep_id AND s.state = 'paused')"


class JobStore(Database):
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
            return new_id(
                conn.execute(
                    "INSERT INTO jobs (kind, state, request_json, sweep_id, created_at, bench, claimed_by, updated_at) "
                    f"VALUES (?, 'queued', ?, ?, ?, ?, ?, {self.dialect.now_text})",
                    (kind, json.dumps(request), sweep_id, now, bench, claimed_by),
                )
            )

    def update_job(self, job_id: int, **fields: Any) -> None:
        self._update_row("jobs", job_id, fields)

    def get_job(self, job_id: int) -> JobRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            return as_record(row) if row else None

    def list_jobs(self, limit: int = 100, kind: str | None = None) -> list[JobRecord]:
        """The newest jobs first (`kind`: of that kind only)."""
        where, args = ("WHERE kind = ? ", (kind, limit)) if kind is not None else ("", (limit,))
        with self.connect() as conn:
            return [as_record(r) for r in conn.execute(f"SELECT * FROM jobs {where}ORDER BY id DESC LIMIT ?", args)]

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

    def bench_unfinished_jobs(self, bench: str) -> list[JobRecord]:
        """This bench's jobs left queued or running, and those of no bench (from before benches: one
        database, one bench)."""
        with self.connect() as conn:
            return [
                as_record(r)
                for r in conn.execute(
                    "SELECT * FROM jobs WHERE state IN ('queued', 'running') AND (bench = ? OR bench IS NULL) "
                    "ORDER BY id",
                    (bench,),
                )
            ]
