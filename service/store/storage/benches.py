"""A lab's benches (table benches, issue 20): each bench name held by one service instance, its
heartbeat, and what the other benches' services wrote (their jobs and sweeps).

Portable SQL only (SQLite and PostgreSQL): `?` placeholders, INSERT ... ON CONFLICT, RETURNING.
Liveness is on the database's clock (issue 25): a heartbeat is stamped, and its age judged, by the
database, never by a bench PC's clock, which may be off by any amount."""

from __future__ import annotations

from typing import Any

from service.store.records import JobRecord, SweepRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, one_row


class BenchStore(Database):
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
            return one_row(cur)

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
                as_record(r)
                for r in conn.execute(
                    f"SELECT *, {self.dialect.seconds_since('last_seen')} AS seen_s FROM benches ORDER BY name"
                )
            ]

    def _bench_row(self, conn: Any, name: str) -> dict[str, Any] | None:
        row = conn.execute(
            f"SELECT *, {self.dialect.seconds_since('last_seen')} AS seen_s FROM benches WHERE name = ?", (name,)
        ).fetchone()
        return as_record(row) if row else None

    def adopt_unnamed_rows(self, bench: str) -> None:
        """Rows from before benches (bench NULL) become this bench's: that database served one bench."""
        with self.transaction() as conn:
            for table in ("jobs", "sweeps", "schedules"):
                conn.execute(f"UPDATE {table} SET bench = ? WHERE bench IS NULL", (bench,))

    def changed_since(self, since: str) -> tuple[list[JobRecord], list[SweepRecord]]:
        """Jobs and sweeps written at or after `since` (UTC ISO on the database's clock), oldest write first."""
        with self.connect() as conn:
            jobs = [
                as_record(r)
                for r in conn.execute("SELECT * FROM jobs WHERE updated_at >= ? ORDER BY updated_at, id", (since,))
            ]
            sweeps = [
                as_record(r)
                for r in conn.execute("SELECT * FROM sweeps WHERE updated_at >= ? ORDER BY updated_at, id", (since,))
            ]
            return jobs, sweeps
