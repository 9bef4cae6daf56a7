"""Maps (tables maps, map_cells) and their validations (table map_validations: the LUT measured in the
drive's LUT mode)."""

from __future__ import annotations

import json
from typing import Any, cast

from service.store.records import MapRecord, MapSummaryRecord, ValidationRecord
from service.store.storage.database import Database
from service.store.storage.rows import as_record, insert_row, new_id, now_iso


class MapStore(Database):
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
        further_orders: list[dict[str, Any]] | None = None,
    ) -> int:
        """A map of `cells` [(result_id, torque, speed, udc)]; `fills` {(torque, speed, udc): Fill} the
        fill rule's entries for cells that are not ok (service/maps/fill.py); `further_orders` [{order, cells}]
        the further orders' cells of a map of several orders, in the order of `cells` (migrations/0013)."""
        fills = fills or {}
        with self.transaction() as conn:
            map_id = new_id(
                conn.execute(
                    "INSERT INTO maps (sweep_id, harmonic_order, method, axes_json, bench_identity, software_version, "
                    "created_at, refined_from, provenance_json, orders_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
                        json.dumps(further_orders) if further_orders else None,
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
                "c.fill_theta_sin, c.fill_source, c.injection_off FROM map_cells c LEFT JOIN results r ON r.id = c.result_id "
                "WHERE c.map_id = ? ORDER BY c.udc_v, c.speed_rpm, c.torque_nm",
                (map_id,),
            ).fetchall()
            return cast(MapRecord, {**as_record(row), "cells": [as_record(c) for c in cells]})

    def set_injection_off(self, map_id: int, cells: list[tuple[float, float, float]], off: bool = True) -> int:
        """Set (off True) or clear injection off on map `map_id`'s cells named by (torque_nm, speed_rpm,
        udc_v): the drive injects nothing in any LUT interval with such a cell as a corner (LUT flag 3).
        All or nothing: ValueError naming the cells the map does not have. Returns the cells changed."""
        with self.transaction() as conn:
            changed = 0
            unknown = []
            for t, n, u in cells:
                row = conn.execute(
                    "SELECT injection_off FROM map_cells WHERE map_id = ? AND torque_nm = ? AND speed_rpm = ? "
                    "AND udc_v = ?",
                    (map_id, t, n, u),
                ).fetchone()
                if row is None:
                    unknown.append((t, n, u))
                    continue
                if bool(row[0]) != off:
                    conn.execute(
                        "UPDATE map_cells SET injection_off = ? WHERE map_id = ? AND torque_nm = ? AND speed_rpm = ? "
                        "AND udc_v = ?",
                        (int(off), map_id, t, n, u),
                    )
                    changed += 1
            if unknown:
                where = "; ".join(f"{t:g} Nm / {n:g} rpm / {u:g} V" for t, n, u in unknown)
                raise ValueError(f"map {map_id} has no cell at {where}")
            return changed

    def list_maps(self, limit: int = 100) -> list[MapSummaryRecord]:
        with self.connect() as conn:
            return [
                as_record(r)
                for r in conn.execute(
                    "SELECT id, sweep_id, harmonic_order, method, created_at FROM maps ORDER BY id DESC LIMIT ?",
                    (limit,),
                )
            ]

    def insert_validation(self, row: dict[str, Any]) -> int:
        with self.transaction() as conn:
            return insert_row(conn, "map_validations", row)

    def update_validation(self, validation_id: int, **fields: Any) -> None:
        self._update_row("map_validations", validation_id, fields)

    def latest_validation(self, map_id: int) -> ValidationRecord | None:
        with self.connect() as conn:
            row = conn.execute(
                "SELECT * FROM map_validations WHERE map_id = ? ORDER BY id DESC LIMIT 1", (map_id,)
            ).fetchone()
            return as_record(row) if row else None

    def validation_of_job(self, job_id: int) -> ValidationRecord | None:
        with self.connect() as conn:
            row = conn.execute("SELECT * FROM map_validations WHERE job_id = ?", (job_id,)).fetchone()
            return as_record(row) if row else None

    def bench_running_validations(self, bench: str) -> list[ValidationRecord]:
        with self.connect() as conn:
            return [
                as_record(r)
                for r in conn.execute(
                    "SELECT v.* FROM map_validations v LEFT JOIN jobs j ON j.id = v.job_id WHERE v.state = 'running' "
                    "AND (j.bench = ? OR j.bench IS NULL)",
                    (bench,),
                )
            ]
