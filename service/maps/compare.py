"""Two maps of one harmonic compared cell by cell (two benches, or one bench a month apart).

Cells are matched on their operating point (the intersection of the two grids; the points only one
map holds are listed). Where both cells are ok:
- delta gamma = gamma_b - gamma_a, delta delta = delta_b - delta_a wrapped to (-180, 180] deg,
  delta theta = |theta_b - theta_a| (theta in rad, docs/conventions.md, Injection and theta; shown in deg);
- the residual map b's theta would leave on map a's bench, from the affine model of the secondary
  path (paper eq. 15; docs/conventions.md, Secondary path: a = S_ss (theta_d + theta)) around map a's measured point:
      a_pred = a_res + S_ss (theta_b - theta_a),   S_ss = [[S_r, S_i], [-S_i, S_r]]
  with a_res the residual phasor map a's result measured at its theta theta_a, and S the secondary
  path that result measured (`s_measured`, full scale per rad); given as
      predicted_suppression_db = 20 log10(|a_uncompensated| / |a_pred|)
  against the uncompensated amplitude of the same result. theta_b = theta_a gives back the measured
  suppression. A result that stored no measured S gets no prediction (said per cell), never a model's.
A filled cell (status not ok, service/maps/fill.py) carries a fill, not a measurement: it is not
compared, and its note says it is filled and where the fill comes from. Axes may differ and be
non-uniform (a refined map inserts breakpoints): the cells meet on their operating points only.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, cast

import numpy as np
from pydantic import BaseModel, Field

from service.errors import Invalid, NotFound
from service.maps.view import MapCell, MapView, map_view
from service.model.operating_point import OperatingPoint
from service.model.secondary_path import s_matrix
from service.store.storage import Storage


class ComplexGain(BaseModel):
    re: float
    im: float
    gain: float = Field(description="|S|, full scale per rad")
    phase_deg: float


class MapCompareCell(BaseModel):
    """One operating point present in both maps (service/maps/compare.py)."""

    torque_nm: float
    speed_rpm: float
    udc_v: float
    status_a: str
    status_b: str
    compared: bool = Field(description="both cells ok (each carries theta)")
    gamma_a_deg: float | None = None
    gamma_b_deg: float | None = None
    delta_a_deg: float | None = None
    delta_b_deg: float | None = None
    delta_gamma_deg: float | None = Field(None, description="gamma_b - gamma_a")
    delta_delta_deg: float | None = Field(None, description="delta_b - delta_a wrapped to (-180, 180]")
    delta_theta_deg: float | None = Field(None, description="|theta_b - theta_a| (theta in rad, shown in deg)")
    suppression_a_db: float | None = Field(None, description="what map a's result measured at its own theta")
    predicted_suppression_db: float | None = Field(
        None,
        description="20 log10(|a_uncompensated| / |a_residual + S_ss (theta_b - theta_a)|) with map a's "
        "measured S, residual and uncompensated phasor (affine model, eq. 15)",
    )
    s_measured_a: ComplexGain | None = None
    note: str | None = Field(None, description="why a cell is not compared, or has no prediction")


class MapCompareSummary(BaseModel):
    compared: int
    not_compared: int = Field(description="in both maps, but not ok in one of them")
    only_in_a: int
    only_in_b: int
    without_s: int = Field(description="compared cells whose map-a result stored no measured S (no prediction)")
    median_delta_theta_deg: float | None = None
    max_delta_theta_deg: float | None = None
    median_abs_delta_gamma_deg: float | None = None
    max_abs_delta_gamma_deg: float | None = None
    median_abs_delta_delta_deg: float | None = None
    max_abs_delta_delta_deg: float | None = None
    worst_cell: OperatingPoint | None = Field(None, description="the compared cell with the largest delta theta")
    median_predicted_suppression_db: float | None = None
    min_predicted_suppression_db: float | None = None
    worst_predicted_cell: OperatingPoint | None = Field(
        None, description="the cell with the lowest predicted suppression"
    )


class MapComparison(BaseModel):
    """`GET /maps/{a}/compare/{b}`: map b's theta against map a's, at the operating points both hold."""

    map_a: int
    map_b: int
    harmonic_order: int
    same_axes: bool = Field(description="false: compared on the intersection of the grids; the rest is listed")
    summary: MapCompareSummary
    cells: list[MapCompareCell]
    only_in_a: list[OperatingPoint]
    only_in_b: list[OperatingPoint]


class MapCompareError(Invalid, ValueError):
    """The two maps cannot be compared (a different harmonic order)."""


def wrap_deg(angle_deg: float) -> float:
    """An angle difference in (-180, 180] deg."""
    return 180.0 - (180.0 - angle_deg) % 360.0


def predicted_suppression_db(
    s_measured: complex,
    residual: tuple[float, float],
    uncompensated_amplitude: float,
    theta_a: tuple[float, float],
    theta_b: tuple[float, float],
) -> float:
    """Suppression (dB) theta_b would reach where theta_a left `residual` ([a_c, a_s], full scale) on a
    path with complex gain `s_measured` (affine model, eq. 15)."""
    a_pred = np.asarray(residual, dtype=float) + s_matrix(s_measured) @ (np.asarray(theta_b) - np.asarray(theta_a))
    return 20.0 * math.log10(max(uncompensated_amplitude, 1e-300) / max(float(np.hypot(*a_pred)), 1e-300))


def compare_maps(storage: Storage, map_a: int, map_b: int) -> MapComparison:
    """Raises NotFound for a map that does not exist, MapCompareError for maps of different harmonics."""
    a, b = map_view(storage, map_a), map_view(storage, map_b)
    for map_id, m in ((map_a, a), (map_b, b)):
        if m is None:
            raise NotFound(f"map {map_id} does not exist")
    assert a is not None and b is not None  # the loop raised otherwise
    if a.harmonic_order != b.harmonic_order:
        raise MapCompareError(
            f"map {map_a} is for harmonic h = {a.harmonic_order} and map {map_b} for "
            f"h = {b.harmonic_order}: their thetas are not comparable"
        )
    results = storage.results_by_id([c.result_id for c in a.cells if c.result_id is not None])
    return compare_views(a, b, results)


def compare_views(a: MapView, b: MapView, results: Mapping[Any, Mapping[str, Any]]) -> MapComparison:
    """Map b against map a, both as the API shows them; `results`: map a's result rows by id (their
    measured S, residual and uncompensated phasor)."""
    map_a, map_b = a.id, b.id
    cells_a, cells_b = _by_point(a), _by_point(b)
    cells = [_cell(map_a, cells_a[k], cells_b[k], results.get(cells_a[k].result_id)) for k in cells_a if k in cells_b]
    return MapComparison(
        map_a=map_a,
        map_b=map_b,
        harmonic_order=a.harmonic_order,
        same_axes=_axes(a) == _axes(b),
        summary=_summary(cells, cells_a, cells_b),
        cells=cells,
        only_in_a=[_op(cells_a[k]) for k in cells_a if k not in cells_b],
        only_in_b=[_op(cells_b[k]) for k in cells_b if k not in cells_a],
    )


Point = tuple[float, float, float]  # a cell's (torque_nm, speed_rpm, udc_v), rounded


def _point(torque_nm: float, speed_rpm: float, udc_v: float) -> Point:
    return (round(float(torque_nm), 6), round(float(speed_rpm), 6), round(float(udc_v), 6))


def _by_point(m: MapView) -> dict[Point, MapCell]:
    return {_point(c.torque_nm, c.speed_rpm, c.udc_v): c for c in m.cells}


def _axes(m: MapView) -> dict[str, list[float]]:
    return {k: sorted(round(float(v), 6) for v in values) for k, values in m.axes.items()}


def _op(c: MapCell | MapCompareCell) -> OperatingPoint:
    return OperatingPoint(torque_nm=c.torque_nm, speed_rpm=c.speed_rpm, udc_v=c.udc_v)


def _cell(map_a: int, ca: MapCell, cb: MapCell, row: Mapping[str, Any] | None) -> MapCompareCell:
    out = MapCompareCell(
        torque_nm=ca.torque_nm,
        speed_rpm=ca.speed_rpm,
        udc_v=ca.udc_v,
        status_a=ca.status,
        status_b=cb.status,
        compared=False,
        suppression_a_db=ca.suppression_db,
    )
    if ca.status != "ok" or cb.status != "ok":
        which = " and ".join(
            f"map {side} has {c.status}" + (f" (filled: {c.fill_source or 'a fill'})" if c.filled else "")
            for side, c in (("a", ca), ("b", cb))
            if c.status != "ok"
        )
        out.note = f"not compared: {which} here (only ok cells carry a measured theta; a fill is not compared)"
        return out
    # both ok: each carries theta, gamma and delta (service/maps/view.py)
    theta_a = cast(tuple[float, float], (ca.theta_cos, ca.theta_sin))
    theta_b = cast(tuple[float, float], (cb.theta_cos, cb.theta_sin))
    gamma_a, gamma_b, delta_a, delta_b = cast(
        tuple[float, float, float, float], (ca.gamma_deg, cb.gamma_deg, ca.delta_deg, cb.delta_deg)
    )
    out.compared = True
    out.gamma_a_deg, out.gamma_b_deg, out.delta_a_deg, out.delta_b_deg = (
        ca.gamma_deg,
        cb.gamma_deg,
        ca.delta_deg,
        cb.delta_deg,
    )
    out.delta_gamma_deg = gamma_b - gamma_a
    out.delta_delta_deg = wrap_deg(delta_b - delta_a)
    out.delta_theta_deg = math.degrees(math.hypot(theta_b[0] - theta_a[0], theta_b[1] - theta_a[1]))
    detail = (row or {}).get("detail") or {}
    s, residual, unc = detail.get("s_measured"), detail.get("residual"), detail.get("uncompensated")
    if s is None or residual is None or unc is None:
        out.note = (
            f"map {map_a}'s result {ca.result_id} stored no measured S (method {(row or {}).get('method')}): "
            "no predicted suppression"
        )
        return out
    assert row is not None  # the detail came from it
    s_complex = complex(s["re"], s["im"])
    out.s_measured_a = ComplexGain(**s)
    # the result's own theta is the point the residual was measured at
    out.predicted_suppression_db = predicted_suppression_db(
        s_complex, (residual["a_c"], residual["a_s"]), unc["amplitude"], (row["theta_cos"], row["theta_sin"]), theta_b
    )
    return out


def _median_max(values: list[float]) -> tuple[float | None, float | None]:
    return (float(np.median(values)), float(np.max(values))) if values else (None, None)


def _summary(
    cells: list[MapCompareCell], cells_a: dict[Point, MapCell], cells_b: dict[Point, MapCell]
) -> MapCompareSummary:
    done = [c for c in cells if c.compared]  # a compared cell has its deltas (_cell)
    predicted = [c for c in done if c.predicted_suppression_db is not None]
    med_theta, max_theta = _median_max([cast(float, c.delta_theta_deg) for c in done])
    med_gamma, max_gamma = _median_max([abs(cast(float, c.delta_gamma_deg)) for c in done])
    med_delta, max_delta = _median_max([abs(cast(float, c.delta_delta_deg)) for c in done])
    worst = max(done, key=lambda c: cast(float, c.delta_theta_deg), default=None)
    worst_predicted = min(predicted, key=lambda c: cast(float, c.predicted_suppression_db), default=None)
    return MapCompareSummary(
        compared=len(done),
        not_compared=len(cells) - len(done),
        only_in_a=sum(1 for k in cells_a if k not in cells_b),
        only_in_b=sum(1 for k in cells_b if k not in cells_a),
        without_s=len(done) - len(predicted),
        median_delta_theta_deg=med_theta,
        max_delta_theta_deg=max_theta,
        median_abs_delta_gamma_deg=med_gamma,
        max_abs_delta_gamma_deg=max_gamma,
        median_abs_delta_delta_deg=med_delta,
        max_abs_delta_delta_deg=max_delta,
        worst_cell=None if worst is None else _op(worst),
        median_predicted_suppression_db=(
            float(np.median([c.predicted_suppression_db for c in predicted])) if predicted else None
        ),
        min_predicted_suppression_db=None if worst_predicted is None else worst_predicted.predicted_suppression_db,
        worst_predicted_cell=None if worst_predicted is None else _op(worst_predicted),
    )
