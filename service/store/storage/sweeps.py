"""Sweeps (table sweeps), refinements included: their rows, the pause / resume / cancel asked of a sweep
through the database (another bench's service acts on it), and what a bench left unfinished."""

from __future__ import annotations

import json
from typing import Any

from service.store.records import SweepRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, new_id, now_iso


class SweepStore(Database):
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
            return new_id(
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
        self._update_row("sweeps", sweep_id, fields)

    def get_sweep(self, sweep_id: int) -> SweepRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM sweeps WHERE id = ?", (sweep_id,)).fetchone()
            return as_record(row) if row else None

    def list_sweeps(self, limit: int = 100) -> list[SweepRecord]:
        with self.connect() as conn:
            return [as_record(r) for r in conn.execute("SELECT * FROM sweeps ORDER BY id DESC LIMIT ?", (limit,))]

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

    def bench_unfinished_sweeps(self, bench: str) -> list[SweepRecord]:
        with self.connect() as conn:
            return [
                as_record(r)
                for r in conn.execute(
                    "SELECT * FROM sweeps WHERE state IN ('queued', 'running', 'paused', 'interrupted') "
                    "AND (bench = ? OR bench IS NULL) ORDER BY id",
                    (bench,),
                )
            ]
