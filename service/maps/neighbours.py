"""Sweeps learn as they go: each point starts from what its neighbours measured.

theta* = -theta_d is the disturbance in injection units: the shaft's G_Salpha cancels out of it, so
it varies smoothly with the operating point even across the shaft resonance, and a neighbour's
theta* puts a new point some 20 dB down before its first step (and brings the sensor into range
next to the resonance). The secondary path S does not share that smoothness in speed (its phase
turns by 180 deg across the resonance), so a measured S is taken only from a cell at the same speed
and DC-link voltage (a plan steps speed innermost: the torque row before has it).
"""

from __future__ import annotations

import math
from typing import Any, cast

from drivers import lut_image
from service.identification.common import Prior
from service.maps.build import best_attempts
from service.maps.fill import MEASURED_MIN_DB, interpolate_between
from service.model.operating_point import OperatingPoint

S2x2 = tuple[tuple[float, float], tuple[float, float]]  # a measured S_ss, fs/rad

# the plane the LUT interpolates in: a prior between two cells is what the drive would inject there
DEFAULT_INTERPOLATION = lut_image.DEFAULT_INTERPOLATION


def prior_from_neighbours(op: OperatingPoint, rows: list[dict[str, Any]], axes: dict[str, list[float]]) -> Prior | None:
    """The prior for `op` from the result rows of the same sweep: theta from the `ok` neighbours (or from
    op's own earlier attempt where it beat the harmonic by MEASURED_MIN_DB), S from an ok neighbour at
    the same speed (None if no row is ok)."""
    ok = [r for r in rows if r["status"] == "ok" and r.get("theta_cos") is not None]
    if not ok:
        return None

    def span(name: str) -> float:
        values = axes.get(name) or [0.0]
        return max(max(values) - min(values), 1e-9)

    def distance(r: dict[str, Any]) -> float:
        return math.sqrt(
            ((r["torque_nm"] - op.torque_nm) / span("torque_nm")) ** 2
            + ((r["speed_rpm"] - op.speed_rpm) / span("speed_rpm")) ** 2
            + ((r["udc_v"] - op.udc_v) / span("udc_v")) ** 2
        )

    nearest = min(ok, key=distance)
    theta = (float(nearest["theta_cos"]), float(nearest["theta_sin"]))
    source = f"neighbour {nearest['torque_nm']:g} Nm / {nearest['speed_rpm']:g} rpm / {nearest['udc_v']:g} V"
    # where ok cells lie on both sides along an axis (a second pass, a refinement), interpolate between them
    between = interpolate_between(
        (op.torque_nm, op.speed_rpm, op.udc_v),
        {(r["torque_nm"], r["speed_rpm"], r["udc_v"]): (float(r["theta_cos"]), float(r["theta_sin"])) for r in ok},
        _axes_with(axes, op),
        DEFAULT_INTERPOLATION,
    )
    if between is not None:
        theta, source = (between.theta_cos, between.theta_sin), between.source
    # a point measured before (a second pass) whose theta beat the harmonic clearly starts from it: a
    # neighbour's, even interpolated, may lie across the field-weakening turn (theta* turns by degrees per rpm)
    own = best_attempts(rows).get((op.torque_nm, op.speed_rpm, op.udc_v))
    if own is not None and own["suppression_db"] >= MEASURED_MIN_DB:
        theta = (float(own["theta_cos"]), float(own["theta_sin"]))
        source = f"its own earlier attempt ({own['status']}, {own['suppression_db']:.1f} dB)"
    same_line = [r for r in ok if r["speed_rpm"] == op.speed_rpm and r["udc_v"] == op.udc_v]
    s_matrix = None
    jacobian: tuple[tuple[float, ...], ...] | None = None
    jacobian_orders: tuple[int, ...] = ()
    if same_line:
        s_row = min(same_line, key=distance)
        details = (s_row.get("detail") or {}).get("details") or {}
        matrix = details.get("s_matrix_refined") or details.get("s_matrix")
        if matrix is not None:
            s_matrix = cast(S2x2, tuple(tuple(float(v) for v in row) for row in matrix))  # 2x2 as stored
            source += f", S from {s_row['torque_nm']:g} Nm"
        # several orders: the whole J the neighbour ended with (probed, then refined by its steps)
        if details.get("jacobian_refined") is not None and details.get("order_list"):
            jacobian = tuple(tuple(float(v) for v in row) for row in details["jacobian_refined"])
            jacobian_orders = tuple(int(h) for h in details["order_list"])
            source += f", J from {s_row['torque_nm']:g} Nm"
    return Prior(theta[0], theta[1], s_matrix, source, further_thetas(nearest), jacobian, jacobian_orders)


def further_thetas(row: dict[str, Any]) -> tuple[tuple[int, float, float], ...]:
    """A result's further orders' theta (method probe-orders), where that order beat its harmonic clearly."""
    orders = ((row.get("detail") or {}).get("details") or {}).get("orders") or []
    return tuple(
        (int(o["order"]), float(o["theta_cos"]), float(o["theta_sin"]))
        for o in orders[1:]
        if o.get("theta_cos") is not None and (o.get("suppression_db") or -1e9) >= MEASURED_MIN_DB
    )


def _axes_with(axes: dict[str, list[float]], op: OperatingPoint) -> dict[str, list[float]]:
    """The axes with op's own values in them (a refinement's new cell lies between the old values)."""
    return {
        name: sorted(set(map(float, axes.get(name) or [])) | {float(getattr(op, name))})
        for name in ("torque_nm", "speed_rpm", "udc_v")
    }
