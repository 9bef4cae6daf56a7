"""Results (table results): one identification's outcome each; a sweep's current result per operating
point (earlier attempts kept as history, superseded_by), its progress counters recounted in the same
transaction, and what became of each result's raw recording."""

from __future__ import annotations

from typing import Any

from service.store.records import ResultRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, insert_row

RECORDING_TABLES = ("results", "runups")  # the tables whose rows carry a raw recording (recording_json)


class ResultStore(Database):
    @property
    def _committed(self) -> str:
        """A sweep's committed results: current (not superseded) and not discarded by an interlock
        (detail_json "discarded" names why; the attempt stays as history and the point is measured again)."""
        return (
            f"sweep_id = ? AND superseded_by IS NULL AND {self.dialect.json_text('detail_json', 'discarded')} IS NULL"
        )

    def insert_result(self, row: dict[str, Any]) -> int:
        """One result in its own transaction. A sweep's result supersedes the earlier attempts at the
        same operating point (kept as history, results.superseded_by) and the sweep's progress
        counters are recounted from its current results, in the same transaction, so a crash between
        two statements cannot leave a point counted twice or a point with two current results."""
        with self.transaction() as conn:
            rid = insert_row(conn, "results", row)
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
            return as_record(row) if row else None

    def results_by_id(self, result_ids: list[int]) -> dict[int, ResultRecord]:
        """The result rows of these ids (ids with no row left out), in one query."""
        ids = sorted({int(i) for i in result_ids})
        if not ids:
            return {}
        with self.connect() as conn:
            return {
                r["id"]: as_record(r)
                for r in conn.execute(f"SELECT * FROM results WHERE id IN ({', '.join('?' for _ in ids)})", ids)
            }

    def set_result_recording(self, result_id: int, record: dict[str, Any]) -> None:
        """What became of the result's raw recording (service/store/recordings/store.py)."""
        self._update_row("results", result_id, {"recording": record})

    def mark_recordings_deleted(self, row_ids: list[int], reason: str, table: str = "results") -> None:
        """Their recordings were deleted (retention): the rows (results, or run-ups) say so, and when."""
        if table not in RECORDING_TABLES:
            raise ValueError(f"{table!r} rows hold no recording")
        with self.transaction() as conn:
            conn.executemany(
                f"UPDATE {table} SET recording_json = {self.dialect.json_set_text('recording_json', 'deleted')} "
                "WHERE id = ? AND recording_json IS NOT NULL",
                [(reason, rid) for rid in row_ids],
            )

    def sweep_results(self, sweep_id: int) -> list[ResultRecord]:
        """The sweep's current results: one per operating point measured (earlier attempts left out)."""
        with self.connect() as conn:
            return [
                as_record(r)
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
                as_record(r) for r in conn.execute("SELECT * FROM results WHERE sweep_id = ? ORDER BY id", (sweep_id,))
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
