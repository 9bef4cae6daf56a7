"""Maps: the compensation over an operating-point grid, assembled from stored results.

A map references one result per grid cell (the latest for that operating point in the sweep);
cells whose identification failed keep their status so exports can mark them invalid.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from drivers import lut_image
from service import __version__
from service.maps.fill import fill_cells
from service.maps.lut_export import map_interpolation
from service.store.storage import Storage


def build_map_from_sweep(storage: Storage, sweep_id: int, cancelled: bool = False) -> int:
    """The sweep's map: the current result of every grid cell, and the fill of those that are not ok. `cancelled`:
    the sweep was cancelled before its end, and the map says it is partial (provenance `partial`)."""
    sweep = storage.get_sweep(sweep_id)
    if sweep is None:
        raise KeyError(f"sweep {sweep_id} does not exist")
    provenance = None
    if cancelled:
        provenance = {
            "partial": f"sweep {sweep_id} was cancelled after {sweep['done_points']} of {sweep['total_points']} "
            "points: the cells not measured are missing (or filled from their neighbours)"
        }
    grid = sweep["grid"]
    axes = {"torque_nm": grid["torque_nm"], "speed_rpm": grid["speed_rpm"], "udc_v": grid["udc_v"]}
    return build_map(
        storage,
        axes,
        storage.sweep_results(sweep_id),
        sweep_id,
        sweep["harmonic_order"],
        sweep["method"],
        sweep["bench_identity"],
        provenance=provenance,
        attempts=storage.sweep_result_history(sweep_id),
    )


def build_map(
    storage: Storage,
    axes: dict[str, list[float]],
    results: Sequence[Mapping[str, Any]],
    sweep_id: int | None,
    harmonic_order: int,
    method: str,
    bench_identity: str,
    refined_from: int | None = None,
    provenance: dict[str, Any] | None = None,
    attempts: Sequence[Mapping[str, Any]] | None = None,
) -> int:
    """A map over `axes` from result rows (the latest per cell wins), with the fill rule applied to the
    cells that are not ok (service/maps/fill.py), in the plane the LUT interpolates in. `attempts`: every
    attempt at the cells (a sweep's history): a non-ok cell's fill may take the theta of its best one
    (a second pass started from a poor prior may end worse than the first did)."""
    latest: dict[tuple[float, float, float], Mapping[str, Any]] = {}
    for row in results:
        latest[(row["torque_nm"], row["speed_rpm"], row["udc_v"])] = row
    best = best_attempts(attempts or [])
    keys = [(t, n, u) for u in axes["udc_v"] for n in axes["speed_rpm"] for t in axes["torque_nm"]]
    cells = [(latest[k]["id"] if k in latest else None, *k) for k in keys]
    interpolation = map_interpolation({"provenance": provenance})  # a refinement's own, else the drive's default
    fills = fill_cells(
        [
            {"torque_nm": k[0], "speed_rpm": k[1], "udc_v": k[2], **_cell_fields(latest.get(k), best.get(k))}
            for k in keys
        ],
        axes,
        interpolation,
    )
    return storage.create_map(
        sweep_id,
        harmonic_order,
        method,
        axes,
        cells,
        bench_identity,
        __version__,
        fills=fills,
        refined_from=refined_from,
        provenance=provenance,
        further_orders=further_order_cells(keys, latest, harmonic_order, axes, interpolation),
    )


ORDER_CELL_FIELDS = ("status", "theta_cos", "theta_sin", "suppression_db", "target_db", "error")


def _orders_of(row: Mapping[str, Any] | None) -> list[Mapping[str, Any]]:
    """A result's orders (method probe-orders: details.orders), [] for a result of one order."""
    return list((((row or {}).get("detail") or {}).get("details") or {}).get("orders") or [])


def further_order_cells(
    keys: Sequence[tuple[float, float, float]],
    latest: Mapping[tuple[float, float, float], Mapping[str, Any]],
    harmonic_order: int,
    axes: dict[str, list[float]],
    interpolation: str = lut_image.DEFAULT_INTERPOLATION,
) -> list[dict[str, Any]]:
    """[{order, cells}] for every order the cells' results carry beside the map's own (in the order the results
    name them), each cell in `keys` order as that order's result judged it (its own status, theta and figure,
    issue 28), with the fill rule applied to that order's cells on their own (service/maps/fill.py); [] for a map
    of one order. A cell whose result does not carry the order (not run, a failure before the identification) is
    that result's status (failed where the result was ok without it), or missing."""
    orders: dict[int, None] = {}
    for k in keys:
        for o in _orders_of(latest.get(k)):
            if int(o["order"]) != harmonic_order:
                orders[int(o["order"])] = None
    further = []
    for h in orders:
        cells = []
        for k in keys:
            row = latest.get(k)
            found = next((o for o in _orders_of(row) if int(o["order"]) == h), None)
            if row is None:
                cell: dict[str, Any] = {"status": "missing"}
            elif found is None:
                status = row["status"] if row["status"] != "ok" else "failed"
                cell = {"status": status, "error": row.get("error") or f"the result carries no order {h}"}
            else:
                cell = {
                    **{f: found.get(f) for f in ORDER_CELL_FIELDS if f != "error"},
                    "error": None if found.get("status") == "ok" else found.get("reason"),
                }
            cells.append(cell)
        fills = fill_cells(
            [{"torque_nm": k[0], "speed_rpm": k[1], "udc_v": k[2], **c} for k, c in zip(keys, cells)],
            axes,
            interpolation,
        )
        for k, cell in zip(keys, cells):
            fill = fills.get(k)
            if fill is not None:
                cell.update(fill_theta_cos=fill.theta_cos, fill_theta_sin=fill.theta_sin, fill_source=fill.source)
        further.append({"order": h, "cells": cells})
    return further


def best_attempts(attempts: Sequence[Mapping[str, Any]]) -> dict[tuple[float, float, float], Mapping[str, Any]]:
    """Per operating point the attempt with a theta that suppressed the harmonic most (attempts an
    interlock discarded do not count: their data were not good)."""
    best: dict[tuple[float, float, float], Mapping[str, Any]] = {}
    for row in attempts:
        if row.get("theta_cos") is None or row.get("suppression_db") is None:
            continue
        if ((row.get("detail") or {}).get("discarded")) is not None:
            continue
        key = (row["torque_nm"], row["speed_rpm"], row["udc_v"])
        if key not in best or row["suppression_db"] > best[key]["suppression_db"]:
            best[key] = row
    return best


def _cell_fields(row: Mapping[str, Any] | None, best: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """What the fill rule sees of a cell: its current result's status, and the theta and figure of its
    best attempt where that suppressed more than the current one (module service/maps/fill.py, rule 1)."""
    if row is None:
        return {"status": "missing"}
    fields = {k: row.get(k) for k in ("status", "theta_cos", "theta_sin", "suppression_db")}
    if best is not None and best["id"] != row["id"] and best["suppression_db"] > (row.get("suppression_db") or -1e9):
        fields.update({k: best[k] for k in ("theta_cos", "theta_sin", "suppression_db")}, attempt_id=best["id"])
    return fields
