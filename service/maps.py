"""Maps: the compensation over an operating-point grid, assembled from stored results.

A map references one result per grid cell (the latest for that operating point in the sweep);
cells whose identification failed keep their status so exports can mark them invalid.
"""
from __future__ import annotations

import json

from service import __version__
from service.storage import Storage

# every cell of a map has one of these; only `ok` cells are valid in a LUT (DESIGN 6)
STATUSES = ("ok", "below_target", "no_authority", "failed", "missing")


def build_map_from_sweep(storage: Storage, sweep_id: int) -> int:
    sweep = storage.get_sweep(sweep_id)
    if sweep is None:
        raise KeyError(f"sweep {sweep_id} does not exist")
    grid = json.loads(sweep["grid_json"])
    latest: dict[tuple[float, float, float], int] = {}
    for row in storage.sweep_results(sweep_id):
        latest[(row["torque_nm"], row["speed_rpm"], row["udc_v"])] = row["id"]
    cells = [(latest.get((t, n, u)), t, n, u)
             for u in grid["udc_v"] for n in grid["speed_rpm"] for t in grid["torque_nm"]]
    axes = {"torque_nm": grid["torque_nm"], "speed_rpm": grid["speed_rpm"], "udc_v": grid["udc_v"]}
    return storage.create_map(sweep_id, sweep["harmonic_order"], sweep["method"], axes, cells,
                              sweep["bench_identity"], __version__)


def public_map(storage: Storage, map_id: int) -> dict | None:
    row = storage.get_map(map_id)
    if row is None:
        return None
    cells = []
    for c in row["cells"]:
        status = c["status"] or "missing"
        ok = status == "ok"
        cells.append({
            "torque_nm": c["torque_nm"], "speed_rpm": c["speed_rpm"], "udc_v": c["udc_v"], "status": status,
            "result_id": c["result_id"],
            "gamma_deg": c["gamma_deg"] if ok else None, "delta_deg": c["delta_deg"] if ok else None,
            "theta_cos": c["theta_cos"] if ok else None, "theta_sin": c["theta_sin"] if ok else None,
            "suppression_db": c["suppression_db"], "target_db": c.get("target_db"),
            "noise_floor_db": c.get("noise_floor_db"), "error": c["error"],
        })
    counts = {status: 0 for status in STATUSES}
    for c in cells:
        counts[c["status"]] = counts.get(c["status"], 0) + 1
    return {"id": row["id"], "sweep_id": row["sweep_id"], "harmonic_order": row["harmonic_order"],
            "status_counts": counts,
            "method": row["method"], "bench_identity": row["bench_identity"],
            "software_version": row["software_version"], "created_at": row["created_at"],
            "axes": json.loads(row["axes_json"]), "cells": cells}
