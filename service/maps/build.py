"""Maps: the compensation over an operating-point grid, assembled from stored results.

A map references one result per grid cell (the latest for that operating point in the sweep);
cells whose identification failed keep their status so exports can mark them invalid.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from drivers import lut_image
from service import __version__
from service.maps.fill import fill_cells
from service.store.storage import Storage


def build_map_from_sweep(storage: Storage, sweep_id: int) -> int:
    """The sweep's map: the current result of every grid cell, and the fill of those that are not ok."""
    sweep = storage.get_sweep(sweep_id)
    if sweep is None:
        raise KeyError(f"sweep {sweep_id} does not exist")
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
    fills = fill_cells(
        [
            {"torque_nm": k[0], "speed_rpm": k[1], "udc_v": k[2], **_cell_fields(latest.get(k), best.get(k))}
            for k in keys
        ],
        axes,
        lut_image.DEFAULT_INTERPOLATION,
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
    )


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
