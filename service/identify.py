"""One identification at one operating point: go there, run the method, leave the bench safe."""
from __future__ import annotations

import json
import math
import threading
from typing import Any

from service import __version__
from service.identification import METHODS, IdentificationResult
from service.identification.common import Conditions, Prior
from service.limits import gamma_max_rad
from service.operating_point import OperatingPoint
from service.secondary_path import model_secondary_path
from service.settings import Settings
from service.storage import now_iso

def parse_options(method: str, options: dict[str, Any] | None):
    """Validated options model for `method` (raises ValueError / pydantic ValidationError)."""
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not available; choose one of {sorted(METHODS)}")
    return METHODS[method].options_model.model_validate(options or {})


class PlantTimeError(ValueError):
    """A method's options would ask for more plant time at one point than the bench allows."""


def check_plant_time(speeds_rpm: list[float], method: str, options, settings: Settings) -> None:
    """Refuse (before queueing) options whose worst case exceeds safety.max_plant_s_per_point at the
    slowest speed asked for (a harmonic period is longest there)."""
    h, pole_pairs = settings.identification.harmonic_order, settings.motor.pole_pairs
    slowest_hz = min(abs(n) for n in speeds_rpm) / 60.0 * pole_pairs * h
    bound_s = options.plant_time_bound_s(slowest_hz)
    limit_s = settings.safety.max_plant_s_per_point
    if bound_s > limit_s:
        raise PlantTimeError(f"{method} options may take up to {bound_s:.0f} s of plant time per operating point "
                             f"(at {min(speeds_rpm):g} rpm), more than safety.max_plant_s_per_point = {limit_s:g} s: "
                             "choose fewer grid points, shorter windows or fewer steps")


def identify_at(bench, settings: Settings, op: OperatingPoint, method: str, options,
                prior: Prior | None = None, cancel: threading.Event | None = None) -> IdentificationResult:
    """Go to `op`, run `method` (starting from `prior` where the method uses one), leave the bench safe.
    `cancel` is the run's cancel token: set, the run stops at its next DAQ read."""
    h = settings.identification.harmonic_order
    gamma_max = gamma_max_rad(options.gamma_max_deg, settings)
    ident = settings.identification
    closed_loop = ident.s_model == "closed_loop" or (ident.s_model == "auto" and not ident.decoupling)
    with bench.operating_point(op, h, gamma_max, cancel=cancel) as session:
        # the model with the shaft mode as learned on this bench so far (sec. 2.3)
        mode = bench.resonance.mode
        s_hat = model_secondary_path(settings, op, h, current_loop=closed_loop,
                                     resonance_pole=complex(mode.sigma_rad_s, mode.omega_rad_s))
        conditions = Conditions(harmonic_frequency_hz=session.harmonic_frequency_hz, resonance_hz=mode.frequency_hz,
                                current_bandwidth_hz=settings.control.bandwidth_hz, decoupling=ident.decoupling)
        result = METHODS[method].run(session, s_hat, options, gamma_max, prior=prior, conditions=conditions)
        result.details["op_settle_plant_s"] = session.op_settle_plant_s
        result.details["stale_samples"] = session.stale_samples
        result.details["speed_rpm_measured"] = session.speed_rpm_measured
        result.details["harmonic_frequency_hz"] = session.harmonic_frequency_hz
        result.details["resonance"] = bench.resonance.snapshot()
    return result


def result_row(op: OperatingPoint, method: str, options, bench_identity: str, started_at: str,
               result: IdentificationResult | None = None, error: str | None = None,
               job_id: int | None = None, sweep_id: int | None = None, harmonic_order: int = 6) -> dict:
    """A `results` row: the outcome (or the error) with everything that describes it."""
    row = {
        "job_id": job_id, "sweep_id": sweep_id,
        "torque_nm": op.torque_nm, "speed_rpm": op.speed_rpm, "udc_v": op.udc_v,
        "harmonic_order": harmonic_order, "method": method,
        "options_json": json.dumps(options.model_dump() if options is not None else {}),
        "bench_identity": bench_identity, "software_version": __version__,
        "started_at": started_at, "finished_at": now_iso(),
    }
    if result is None:
        row.update({"status": "failed", "error": error or "unknown error"})
        return row
    pub = result.to_public()
    row.update({
        "status": result.status, "error": None if result.status == "ok" else result.message,
        "theta_cos": result.theta_cos, "theta_sin": result.theta_sin,
        "gamma_deg": result.gamma_deg, "delta_deg": result.delta_deg,
        "residual_a_c": result.residual.a_c, "residual_a_s": result.residual.a_s,
        "uncompensated_a_c": result.uncompensated.a_c, "uncompensated_a_s": result.uncompensated.a_s,
        "suppression_db": result.suppression_db, "plant_time_s": result.plant_time_s,
        "windows_used": result.windows_used, "target_db": result.target_db, "noise_floor_db": result.noise_floor_db,
        "detail_json": json.dumps({k: pub[k] for k in ("message", "residual", "uncompensated", "s_model", "s_measured",
                                                       "details", "windows_discarded")}),
        "traces_json": json.dumps(result.traces),
    })
    return row


def public_result(row: dict) -> dict:
    """API view of a stored result row."""
    detail = json.loads(row.get("detail_json") or "{}")
    return {
        "id": row["id"], "status": row["status"], "error": row["error"], "method": row["method"],
        "message": detail.get("message"),
        "operating_point": {"torque_nm": row["torque_nm"], "speed_rpm": row["speed_rpm"], "udc_v": row["udc_v"]},
        "harmonic_order": row["harmonic_order"],
        "gamma_deg": row.get("gamma_deg"), "delta_deg": row.get("delta_deg"),
        "theta_cos": row.get("theta_cos"), "theta_sin": row.get("theta_sin"),
        "residual": detail.get("residual"), "uncompensated": detail.get("uncompensated"),
        "suppression_db": row.get("suppression_db"), "target_db": row.get("target_db"),
        "noise_floor_db": row.get("noise_floor_db"), "plant_time_s": row.get("plant_time_s"),
        "windows_used": row.get("windows_used"), "windows_discarded": detail.get("windows_discarded"),
        "s_model": detail.get("s_model"), "s_measured": detail.get("s_measured"), "details": detail.get("details"),
        "options": json.loads(row["options_json"]), "bench_identity": row["bench_identity"],
        "software_version": row["software_version"], "started_at": row["started_at"], "finished_at": row["finished_at"],
        "traces": json.loads(row.get("traces_json") or "{}"),
    }
