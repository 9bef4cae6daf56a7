"""Maps: the compensation over an operating-point grid, assembled from stored results.

A map references one result per grid cell (the latest for that operating point in the sweep);
cells whose identification failed keep their status so exports can mark them invalid.
"""

from __future__ import annotations

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
    )


def build_map(
    storage: Storage,
    axes: dict[str, list[float]],
    results: list[dict],
    sweep_id: int | None,
    harmonic_order: int,
    method: str,
    bench_identity: str,
    refined_from: int | None = None,
    provenance: dict | None = None,
) -> int:
    """A map over `axes` from result rows (the latest per cell wins), with the fill rule applied to the
    cells that are not ok (service/maps/fill.py), in the plane the LUT interpolates in."""
    latest: dict[tuple[float, float, float], dict] = {}
    for row in results:
        latest[(row["torque_nm"], row["speed_rpm"], row["udc_v"])] = row
    keys = [(t, n, u) for u in axes["udc_v"] for n in axes["speed_rpm"] for t in axes["torque_nm"]]
    cells = [(latest[k]["id"] if k in latest else None, *k) for k in keys]
    fills = fill_cells(
        [{"torque_nm": k[0], "speed_rpm": k[1], "udc_v": k[2], **_cell_fields(latest.get(k))} for k in keys],
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


def _cell_fields(row: dict | None) -> dict:
    if row is None:
        return {"status": "missing"}
    return {k: row.get(k) for k in ("status", "theta_cos", "theta_sin", "suppression_db")}
