"""A stored map as the layers above the database read it: each cell's status, its theta (ok cells;
a fill where the fill rule gave one, service/maps/fill.py), each ok cell's quality against its
neighbours (service/maps/quality.py) and, on request, the smoothed view. The LUT, its exports, the
download, the validation and the comparison all read a map through `map_view`; the API publishes it
(service/api/public/maps.py adds the latest validation)."""

from __future__ import annotations

import math
from typing import Any, cast

from pydantic import BaseModel, Field

from service.maps import quality as map_quality
from service.model.secondary_path import gamma_delta
from service.store.storage import Storage

# every cell of a map has one of these; only `ok` cells are valid in a LUT (docs/conventions.md, Statuses)
RESULT_STATUSES = ("ok", "below_target", "no_authority", "failed")
CELL_STATUSES = (*RESULT_STATUSES, "missing")


class MapCell(BaseModel):
    torque_nm: float
    speed_rpm: float
    udc_v: float
    status: str = Field(description="ok | below_target | no_authority | failed | missing; only ok is valid in a LUT")
    result_id: int | None = None
    gamma_deg: float | None = None
    delta_deg: float | None = None
    theta_cos: float | None = None
    theta_sin: float | None = None
    suppression_db: float | None = None
    target_db: float | None = None
    noise_floor_db: float | None = None
    error: str | None = None
    quality: str | None = Field(
        None,
        description="ok cells only: consistent | outlier | unchecked (fewer than 2 ok "
        "neighbours) | smoothed (a smoothed view replaced the measured theta); "
        "service/maps/quality.py",
    )
    outlier_reason: str | None = Field(None, description="outlier or smoothed: how far theta is from its neighbours'")
    smoothed_from: str | None = Field(None, description="smoothed: where the theta shown comes from")
    filled: bool = Field(
        False,
        description="a cell that is not ok but carries a LUT entry by the fill rule "
        "(service/maps/fill.py): theta_cos/theta_sin are the fill, never a result at its target; "
        "every export flags it apart from valid, and a download takes it only with fill",
    )
    fill_source: str | None = Field(None, description="filled cells: where the theta comes from")
    injection_off: bool = Field(
        False,
        description="the drive injects nothing in any LUT interval that has this cell as a corner of "
        "non-zero weight (LUT flag 3, drivers/lut_image.py: never worse than no compensation where "
        "interpolation misses theta*); the cell keeps its theta for the record",
    )


class MapQuality(BaseModel):
    """Each ok cell's theta against its grid neighbours' (service/maps/quality.py has the statistic)."""

    consistent: int
    outliers: int
    unchecked: int = Field(description="ok cells with fewer than 2 ok neighbours to compare with")
    smoothed: int = Field(0, description="outliers replaced by their neighbours' fit in this (smoothed) view")
    outlier_factor: float = Field(
        description="an outlier is this many times further from its neighbours' "
        "median than the step the map's median gradient expects"
    )
    min_step_deg: float = Field(description="the expected step is never taken below this")
    gradient_deg_per_unit: dict[str, float | None] = Field(
        description="median |delta theta| between ok neighbours per Nm, per rpm, per V (null: no pair on that axis)"
    )


class OrderMap(BaseModel):
    """A further order of a map of several orders (issue 28): its cells as that order's results judged them,
    with the fill rule applied to that order on its own; the map's own order is the map's cells."""

    order: int = Field(description="electrical order")
    status_counts: dict[str, int]
    filled_cells: int = 0
    cells: list[MapCell]


class MapView(BaseModel):
    """A stored map as every layer reads it: its cells (fill and quality applied), no validation."""

    id: int
    sweep_id: int | None = None
    harmonic_order: int
    method: str
    bench_identity: str
    software_version: str
    created_at: str
    axes: dict[str, list[float]]
    status_counts: dict[str, int]
    cells: list[MapCell]
    quality: MapQuality | None = None
    smoothed: bool = Field(
        False,
        description="true: a view whose outlier cells carry their neighbours' fit "
        "(?smooth=outliers); the stored map is never changed",
    )
    filled_cells: int = Field(0, description="cells not ok that carry a fill (service/maps/fill.py)")
    injection_off_cells: int = Field(0, description="cells with injection off (MapCell.injection_off)")
    refined_from: int | None = Field(None, description="a refined map: the map it was refined from")
    provenance: dict[str, Any] | None = Field(
        None, description="how a refined map was made: refinement, rounds, cells added"
    )
    partial: str | None = Field(
        None, description="a map of a sweep cancelled before its end: what was measured (the rest is missing or filled)"
    )
    orders: list[int] = Field(
        default_factory=list, description="the harmonic orders the map compensates, its own (harmonic_order) first"
    )
    further_orders: list[OrderMap] = Field(
        default_factory=list,
        description="the orders after the first, each with its own cells (the first's are `cells`)",
    )


def _cell(record: dict[str, Any]) -> MapCell:
    """A map cell from its stored record: ok cells carry their theta, others their fill where the rule gave one."""
    status = record.get("status") or "missing"
    ok = status == "ok"
    theta = (record.get("theta_cos"), record.get("theta_sin")) if ok else (None, None)
    cell = MapCell(
        torque_nm=record["torque_nm"],
        speed_rpm=record["speed_rpm"],
        udc_v=record["udc_v"],
        status=status,
        result_id=record.get("result_id"),
        theta_cos=theta[0],
        theta_sin=theta[1],
        suppression_db=record.get("suppression_db"),
        target_db=record.get("target_db"),
        noise_floor_db=record.get("noise_floor_db"),
        error=record.get("error"),
        injection_off=bool(record.get("injection_off")),
    )
    if not ok and record.get("fill_theta_cos") is not None:  # the fill rule's entry (service/maps/fill.py)
        cell.theta_cos, cell.theta_sin = record["fill_theta_cos"], record["fill_theta_sin"]
        cell.filled, cell.fill_source = True, record["fill_source"]
    if ok and record.get("gamma_deg") is not None:  # as the result stored them
        cell.gamma_deg, cell.delta_deg = record["gamma_deg"], record["delta_deg"]
    elif cell.theta_cos is not None and cell.theta_sin is not None:
        cell.gamma_deg, cell.delta_deg = (math.degrees(v) for v in gamma_delta(cell.theta_cos, cell.theta_sin))
    return cell


def _status_counts(cells: list[MapCell]) -> dict[str, int]:
    counts = {status: 0 for status in CELL_STATUSES}
    for c in cells:
        counts[c.status] = counts.get(c.status, 0) + 1
    return counts


def _further_orders(row: dict[str, Any]) -> list[OrderMap]:
    """The further orders of a stored map (migrations/0013), each cell placed at its map cell's point."""
    further = []
    for entry in row.get("orders") or []:
        cells = [
            _cell({**{a: main[a] for a in ("torque_nm", "speed_rpm", "udc_v", "result_id")}, **cell})
            for main, cell in zip(row["cells"], entry["cells"])
        ]
        further.append(
            OrderMap(
                order=entry["order"],
                status_counts=_status_counts(cells),
                filled_cells=sum(1 for c in cells if c.filled),
                cells=cells,
            )
        )
    return further


def order_map(m: dict[str, Any], order: int) -> dict[str, Any]:
    """The map (MapView.model_dump()) as a map of one order, `order`: its own order is the map itself; a further
    order's is the map with that order's cells (every export and the LUT image of one order read it)."""
    if order == m["harmonic_order"]:
        return {**m, "orders": [order], "further_orders": []}
    for entry in m.get("further_orders") or []:
        if entry["order"] == order:
            return {
                **m,
                "harmonic_order": order,
                "cells": entry["cells"],
                "status_counts": entry["status_counts"],
                "filled_cells": entry["filled_cells"],
                "injection_off_cells": 0,
                "orders": [order],
                "further_orders": [],
            }
    raise KeyError(f"map {m['id']} has no order {order}; its orders are {m.get('orders') or [m['harmonic_order']]}")


def map_view(storage: Storage, map_id: int, smooth: bool = False) -> MapView | None:
    """The stored map with each ok cell's quality; `smooth`: the view whose outlier cells carry their
    neighbours' fit instead of the measured theta (marked `smoothed`, the stored map is not changed)."""
    row = storage.get_map(map_id)
    if row is None:
        return None
    cells = [_cell(cast(dict[str, Any], record)) for record in row["cells"]]
    counts = _status_counts(cells)
    axes = row["axes"]
    quality = map_quality.assess([c.model_dump() for c in cells], axes)
    smoothed = {}
    if smooth:
        smoothed = map_quality.smoothing(
            quality, map_id, {map_quality.cell_key(c.model_dump()): c.result_id for c in cells}
        )
        for c in cells:
            key = map_quality.cell_key(c.model_dump())
            if key in smoothed:
                (c.theta_cos, c.theta_sin), c.smoothed_from = smoothed[key]
                c.outlier_reason, c.quality = quality.cells[key].reason, "smoothed"
                c.gamma_deg, c.delta_deg = (math.degrees(v) for v in gamma_delta(c.theta_cos, c.theta_sin))
                c.suppression_db = None  # measured at the replaced theta, not at this one
        quality = map_quality.assess([c.model_dump() for c in cells], axes)
    for c in cells:
        q = quality.cells.get(map_quality.cell_key(c.model_dump()))
        if q is not None and c.quality is None:
            c.quality, c.outlier_reason = q.quality, q.reason
    summary = MapQuality(
        consistent=sum(1 for c in cells if c.quality == "consistent"),
        outliers=sum(1 for c in cells if c.quality == "outlier"),
        unchecked=sum(1 for c in cells if c.quality == "unchecked"),
        smoothed=len(smoothed),
        outlier_factor=map_quality.OUTLIER_FACTOR,
        min_step_deg=map_quality.MIN_STEP_DEG,
        gradient_deg_per_unit={
            a: None if g is None else math.degrees(g) for a, g in quality.gradient_rad_per_unit.items()
        },
    )
    return MapView(
        id=row["id"],
        sweep_id=row["sweep_id"],
        harmonic_order=row["harmonic_order"],
        method=row["method"],
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        created_at=row["created_at"],
        axes=axes,
        status_counts=counts,
        cells=cells,
        filled_cells=sum(1 for c in cells if c.filled),
        injection_off_cells=sum(1 for c in cells if c.injection_off),
        refined_from=row.get("refined_from"),
        provenance=row.get("provenance"),
        quality=summary,
        smoothed=smooth,
        partial=(row.get("provenance") or {}).get("partial"),
        further_orders=(further := _further_orders(cast(dict[str, Any], row))),
        orders=[row["harmonic_order"], *(o.order for o in further)],
    )
