"""A result as the database keeps it: the one place where an identification's outcome, or the
reason it has none, becomes a `results` row (its columns, with `options`, `detail` and `traces` as the JSON the store
encodes into their `_json` columns).

A result has three shapes and no more: `IdentificationResult` (what a method returns), this row,
and the API's `ResultPublic` (service/api/public.py), read back from the row.
"""

from __future__ import annotations

import math
from typing import Any

from service import __version__
from service.identification import IdentificationResult
from service.model.operating_point import OperatingPoint
from service.store.storage import now_iso


def complex_gain(c: complex | None) -> dict[str, float] | None:
    """A complex gain (S, 1) as results keep it: re, im, gain and phase in degrees."""
    return (
        None
        if c is None
        else {"re": c.real, "im": c.imag, "gain": abs(c), "phase_deg": math.degrees(math.atan2(c.imag, c.real))}
    )


def result_row(
    op: OperatingPoint,
    method: str,
    options: Any,
    bench_identity: str,
    started_at: str,
    result: IdentificationResult | None = None,
    error: str | None = None,
    job_id: int | None = None,
    sweep_id: int | None = None,
    harmonic_order: int = 6,
    detail: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A `results` row: the outcome (or the error, with `detail` saying more: e.g. the interlock that
    discarded the point, or the sweep pass it failed in) with everything that describes it."""
    row = {
        "job_id": job_id,
        "sweep_id": sweep_id,
        "torque_nm": op.torque_nm,
        "speed_rpm": op.speed_rpm,
        "udc_v": op.udc_v,
        "harmonic_order": harmonic_order,
        "method": method,
        "options": options.model_dump() if options is not None else {},
        "bench_identity": bench_identity,
        "software_version": __version__,
        "started_at": started_at,
        "finished_at": now_iso(),
    }
    if result is None:
        row.update({"status": "failed", "error": error or "unknown error"})
        if detail is not None:
            row["detail"] = detail
        return row
    detail = {
        "message": result.message,
        "residual": result.residual.as_dict(),
        "uncompensated": result.uncompensated.as_dict(),
        "s_model": complex_gain(result.s_model),
        "s_measured": complex_gain(result.s_measured),
        "details": result.details,
        "windows_discarded": result.windows_discarded,
    }
    row.update(
        {
            "status": result.status,
            "error": None if result.status == "ok" else result.message,
            "theta_cos": result.theta_cos,
            "theta_sin": result.theta_sin,
            "gamma_deg": result.gamma_deg,
            "delta_deg": result.delta_deg,
            "residual_a_c": result.residual.a_c,
            "residual_a_s": result.residual.a_s,
            "uncompensated_a_c": result.uncompensated.a_c,
            "uncompensated_a_s": result.uncompensated.a_s,
            "suppression_db": result.suppression_db,
            "plant_time_s": result.plant_time_s,
            "windows_used": result.windows_used,
            "target_db": result.target_db,
            "noise_floor_db": result.noise_floor_db,
            "torque_actual_nm": result.torque_actual_nm,
            "detail": detail,
            "traces": result.traces,
        }
    )
    return row
