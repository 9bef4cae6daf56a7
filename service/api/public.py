"""The public shapes (the Public schema family) and their mapping from storage, in one place.

A result has three shapes and no more: `IdentificationResult` (what a method returns), its storage
row (`result_row`, the columns of `results` plus `detail_json` / `traces_json`) and `ResultPublic`
(what the API, the SSE events and the CLI show). Jobs, sweeps and maps likewise have one Public model
each, built here from their rows; routes return these models, so /docs shows every field.
"""
from __future__ import annotations

import json
import math
from datetime import datetime
from typing import Any
from zoneinfo import ZoneInfo

from pydantic import BaseModel, Field

from service import __version__
from service.maps import quality as map_quality
from service.identification import IdentificationResult
from service.model.operating_point import OperatingPoint
from service.store.recordings import recording_record, unavailable_reason
from service.runs.schedules import iso, next_runs
from service.model.secondary_path import gamma_delta
from service.store.storage import Storage, now_iso

# every cell of a map has one of these; only `ok` cells are valid in a LUT (DESIGN 6)
RESULT_STATUSES = ("ok", "below_target", "no_authority", "failed")
CELL_STATUSES = (*RESULT_STATUSES, "missing")


class PhasorPublic(BaseModel):
    a_c: float = Field(description="(2/N) sum(alpha cos(h phi_e)), sensor full scale")
    a_s: float = Field(description="(2/N) sum(alpha sin(h phi_e)), sensor full scale")
    amplitude: float


class ComplexGainPublic(BaseModel):
    re: float
    im: float
    gain: float = Field(description="|S|, full scale per rad")
    phase_deg: float


class RecordingPublic(BaseModel):
    """The raw recording of one identification (DAQ samples and theta setpoints, MF4)."""
    available: bool = Field(description="the file can be downloaded (url)")
    format: str = Field("mf4", description="mf4: ASAM MDF 4.10")
    url: str | None = Field(None, description="GET it here while available")
    bytes: int | None = None
    samples: int | None = Field(None, description="DAQ samples in the file: those counted in plant_time_s "
                                "(samples = plant_time_s x sample_rate_hz when the DAQ lost none)")
    stale_samples: int | None = Field(None, description="samples read before a setpoint took effect: counted, not in the file")
    setpoints: int | None = Field(None, description="theta setpoints, each with the sample at which it took effect")
    sample_rate_hz: float | None = None
    error: str | None = Field(None, description="why it is not available: the write failed (and why), or retention deleted it")


class ResultPublic(BaseModel):
    """One identification at one operating point, self-describing (DESIGN 6)."""
    id: int
    status: str = Field(description="ok (met target_db) | below_target | no_authority | failed")
    error: str | None = Field(None, description="for every status but ok: the reason a test engineer can act on")
    message: str | None = None
    method: str
    operating_point: OperatingPoint
    harmonic_order: int
    gamma_deg: float | None = None
    delta_deg: float | None = None
    theta_cos: float | None = Field(None, description="rad")
    theta_sin: float | None = Field(None, description="rad")
    residual: PhasorPublic | None = None
    uncompensated: PhasorPublic | None = None
    suppression_db: float | None = None
    target_db: float | None = None
    noise_floor_db: float | None = Field(None, description="rms noise phasor of the final window against |uncompensated|")
    plant_time_s: float | None = Field(None, description="DAQ samples / rate, counted from each setpoint's effect")
    windows_used: int | None = None
    windows_discarded: int | None = None
    s_model: ComplexGainPublic | None = None
    s_measured: ComplexGainPublic | None = None
    details: dict[str, Any] | None = None
    options: dict[str, Any]
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str
    traces: dict[str, Any] = Field(default_factory=dict, description="data to redraw the result's plots")
    recording: RecordingPublic | None = Field(None, description="its raw recording (null: none was attempted)")


class JobPublic(BaseModel):
    id: int
    kind: str
    state: str
    request: dict[str, Any]
    sweep_id: int | None = None
    error: str | None = None
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    result: "ResultPublic | RefinementPublic | None" = Field(None, description="kind identification: the result; kind "
                                                           "refinement: the refined map, its rounds, the cells added "
                                                           "and the final validation")
    validation: "ValidationPublic | None" = Field(None, description="kind validation: the map's LUT measured in "
                                                                   "the drive's LUT mode, every cell")


class RefinementRoundPublic(BaseModel):
    round: int = Field(description="0: the source map (its non-ok cells measured again first); k: after k insertions")
    map_id: int = Field(description="the map validated in this round")
    validation_id: int | None = None
    points: int = Field(description="validation points (grid points and midpoints)")
    below_target: int = Field(description="points below the target (or not measured)")
    grid_median_db: float | None = None
    midpoint_median_db: float | None = None
    min_db: float | None = None
    inserted: dict[str, list[float]] = Field(default_factory=dict, description="axis values inserted after it")
    remeasured: int = Field(0, description="cells identified again after it (their LUT entry missed at the cell)")
    new_cells: int = Field(0, description="cells the inserted values added")


class RefinementPublic(BaseModel):
    """A map refined on the drive until its LUT holds (service/runs/refinement.py)."""
    refinement_id: int = Field(description="its sweep (kind refinement): pause, resume, cancel there")
    source_map_id: int
    map_id: int = Field(description="the refined map (the latest round's)")
    state: str
    phase: str = Field(description="measure | validate | done")
    target_db: float
    max_cells: int
    cells_added: int = Field(description="cells identified by the refinement (new and re-measured)")
    holds: bool = Field(description="every point of the latest validation reached target_db")
    stopped: str | None = Field(None, description="why it ended before every point held (budget, rounds)")
    rounds: list[RefinementRoundPublic]
    validation: "ValidationSummaryPublic | None" = Field(None, description="the latest validation of map_id")


class SweepPointPublic(BaseModel):
    operating_point: OperatingPoint
    state: str = Field(description="the result's status")
    error: str | None = None
    result: ResultPublic


class SweepPublic(BaseModel):
    id: int
    state: str
    method: str
    harmonic_order: int
    grid: dict[str, Any]
    options: dict[str, Any]
    progress: dict[str, int] = Field(description="done, failed, total, and the current results per status: "
                                     "ok, below_target, no_authority, failed")
    plant_time_s: float = Field(0.0, description="plant time of the current results, summed (s)")
    map_id: int | None = None
    error: str | None = None
    pause_reason: str | None = None
    bench_identity: str
    software_version: str
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    schedule_id: int | None = Field(None, description="the schedule that submitted this sweep (none: started by hand)")
    kind: str = Field("sweep", description="sweep | refinement (a map refined on the drive: see `refinement`)")
    refinement: RefinementPublic | None = None
    points: list[SweepPointPublic] | None = None


class MapCellPublic(BaseModel):
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
    quality: str | None = Field(None, description="ok cells only: consistent | outlier | unchecked (fewer than 2 ok "
                                "neighbours) | smoothed (a smoothed view replaced the measured theta); "
                                "service/maps/quality.py")
    outlier_reason: str | None = Field(None, description="outlier or smoothed: how far theta is from its neighbours'")
    smoothed_from: str | None = Field(None, description="smoothed: where the theta shown comes from")
    filled: bool = Field(False, description="a cell that is not ok but carries a LUT entry by the fill rule "
                         "(service/maps/fill.py): theta_cos/theta_sin are the fill, never a result at its target; "
                         "every export flags it apart from valid, and a download takes it only with fill")
    fill_source: str | None = Field(None, description="filled cells: where the theta comes from")


class MapQualityPublic(BaseModel):
    """Each ok cell's theta against its grid neighbours' (service/maps/quality.py has the statistic)."""
    consistent: int
    outliers: int
    unchecked: int = Field(description="ok cells with fewer than 2 ok neighbours to compare with")
    smoothed: int = Field(0, description="outliers replaced by their neighbours' fit in this (smoothed) view")
    outlier_factor: float = Field(description="an outlier is this many times further from its neighbours' "
                                  "median than the step the map's median gradient expects")
    min_step_deg: float = Field(description="the expected step is never taken below this")
    gradient_deg_per_unit: dict[str, float | None] = Field(
        description="median |delta theta| between ok neighbours per Nm, per rpm, per V (null: no pair on that axis)")


class MapPublic(BaseModel):
    id: int
    sweep_id: int | None = None
    harmonic_order: int
    method: str
    bench_identity: str
    software_version: str
    created_at: str
    axes: dict[str, list[float]]
    status_counts: dict[str, int]
    cells: list[MapCellPublic]
    quality: MapQualityPublic | None = None
    smoothed: bool = Field(False, description="true: a view whose outlier cells carry their neighbours' fit "
                           "(?smooth=outliers); the stored map is never changed")
    validation: "ValidationSummaryPublic | None" = Field(None, description="the latest validation in the drive's "
                                                                         "LUT mode (cells: GET /maps/{id}/validation)")
    filled_cells: int = Field(0, description="cells not ok that carry a fill (service/maps/fill.py)")
    refined_from: int | None = Field(None, description="a refined map: the map it was refined from")
    provenance: dict[str, Any] | None = Field(None, description="how a refined map was made: refinement, rounds, "
                                              "cells added")


class MapSummaryPublic(BaseModel):
    id: int
    sweep_id: int | None = None
    harmonic_order: int
    method: str
    created_at: str


class ScheduleRunPublic(BaseModel):
    """One firing of a schedule and what came of it."""
    id: int
    due_at: str = Field(description="when it fell due, ISO 8601 in the schedule's time zone")
    fired_at: str = Field(description="when the scheduler handled it, ISO 8601 in the schedule's time zone")
    outcome: str = Field(description="started (the bench was free) | queued (behind a run in progress) | skipped "
                                     "(this schedule's previous sweep still waits) | missed (the service was down "
                                     "longer than schedules.missed_grace_s) | failed (the sweep was refused)")
    sweep_id: int | None = None
    sweep_state: str | None = Field(None, description="the state of that sweep now")
    note: str | None = None


class SchedulePublic(BaseModel):
    id: int
    name: str
    cron: str = Field(description="5 fields: minute hour day-of-month month day-of-week (Debian cron)")
    timezone: str = Field(description="IANA time zone the cron is read in")
    sweep: dict[str, Any] = Field(description="the sweep each firing submits: grid, method, options, confirm_large")
    enabled: bool
    created_at: str
    updated_at: str
    next_runs: list[str] = Field(description="the next firings, ISO 8601 with offset (empty while disabled)")
    runs: list[ScheduleRunPublic] = Field(description="recent firings, newest first")


class SchedulePreviewPublic(BaseModel):
    cron: str
    timezone: str
    runs: list[str] = Field(description="the firings after `start`, ISO 8601 with the zone's offset")



class MapCompareCellPublic(BaseModel):
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
        None, description="20 log10(|a_uncompensated| / |a_residual + S_ss (theta_b - theta_a)|) with map a's "
                          "measured S, residual and uncompensated phasor (affine model, eq. 15)")
    s_measured_a: ComplexGainPublic | None = None
    note: str | None = Field(None, description="why a cell is not compared, or has no prediction")


class MapCompareSummaryPublic(BaseModel):
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
    worst_predicted_cell: OperatingPoint | None = Field(None, description="the cell with the lowest predicted suppression")


class MapComparisonPublic(BaseModel):
    """`GET /maps/{a}/compare/{b}`: map b's theta against map a's, at the operating points both hold."""
    map_a: int
    map_b: int
    harmonic_order: int
    same_axes: bool = Field(description="false: compared on the intersection of the grids; the rest is listed")
    summary: MapCompareSummaryPublic
    cells: list[MapCompareCellPublic]
    only_in_a: list[OperatingPoint]
    only_in_b: list[OperatingPoint]


class ValidationCellPublic(BaseModel):
    """One point of a validation: a grid point or an untrained midpoint, measured in the drive's LUT mode."""
    operating_point: OperatingPoint
    kind: str = Field(description="grid (a trained cell) | midpoint (between neighbouring grid values: interpolated)")
    status: str = Field(description="measured | failed (error says why) | not_measured (the run stopped first)")
    error: str | None = None
    suppression_db: float | None = Field(None, description="20 log10(|uncompensated| / |residual|), only if measured")
    uncompensated: PhasorPublic | None = Field(None, description="injection off")
    residual: PhasorPublic | None = Field(None, description="the drive's own LUT feedforward (injection mode 2)")
    noise_floor_db: float | None = Field(None, description="rms noise phasor of the LUT window against |uncompensated|")
    at_noise_floor: bool | None = Field(None, description="the residual is within 3 noise rms of zero: "
                                                          "suppression_db is a lower bound")
    plant_time_s: float | None = None
    speed_rpm_measured: float | None = None
    harmonic_frequency_hz: float | None = None
    map_cell_status: str | None = Field(None, description="grid points: the map cell's status")
    map_cell_filled: bool | None = Field(None, description="grid points: the cell went into the LUT with its fill "
                                         "(not ok, service/maps/fill.py)")
    bench_time_s: dict[str, float] | None = Field(None, description="wall seconds of the point by what they were "
                                                  "spent on: move, accounting, settle, measurement")


class ValidationSummaryPublic(BaseModel):
    """A validation's figures: per kind (grid, midpoint) the cells, how many were measured, failed or
    not measured, and the median / minimum suppression of the measured ones (dB); the worst cell."""
    id: int
    job_id: int
    map_id: int
    state: str = Field(description="running (stored as it measures) | done | failed (interlock, error or the "
                                   "service stopped: see error) | cancelled")
    error: str | None = None
    finished_at: str | None = None
    download: dict[str, Any] | None = Field(None, description="the LUT download's receipt (bytes, CRC-32 read back)")
    grid: dict[str, Any]
    midpoint: dict[str, Any]
    worst: dict[str, Any] | None = None
    plant_time_s: float


class ValidationPublic(ValidationSummaryPublic):
    harmonic_order: int
    options: dict[str, Any]
    bench_identity: str
    software_version: str
    started_at: str
    cells: list[ValidationCellPublic]


JobPublic.model_rebuild()       # their `validation` fields name the models defined above
RefinementPublic.model_rebuild()
SweepPublic.model_rebuild()
MapPublic.model_rebuild()


# --- results: domain -> row -> public ---------------------------------------------------------------
def _complex(c: complex | None) -> dict | None:
    return None if c is None else {"re": c.real, "im": c.imag, "gain": abs(c),
                                   "phase_deg": math.degrees(math.atan2(c.imag, c.real))}


def _phasor(p) -> dict:
    return {"a_c": p.a_c, "a_s": p.a_s, "amplitude": p.amplitude}


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
    detail = {"message": result.message, "residual": _phasor(result.residual),
              "uncompensated": _phasor(result.uncompensated), "s_model": _complex(result.s_model),
              "s_measured": _complex(result.s_measured), "details": result.details,
              "windows_discarded": result.windows_discarded}
    row.update({
        "status": result.status, "error": None if result.status == "ok" else result.message,
        "theta_cos": result.theta_cos, "theta_sin": result.theta_sin,
        "gamma_deg": result.gamma_deg, "delta_deg": result.delta_deg,
        "residual_a_c": result.residual.a_c, "residual_a_s": result.residual.a_s,
        "uncompensated_a_c": result.uncompensated.a_c, "uncompensated_a_s": result.uncompensated.a_s,
        "suppression_db": result.suppression_db, "plant_time_s": result.plant_time_s,
        "windows_used": result.windows_used, "target_db": result.target_db, "noise_floor_db": result.noise_floor_db,
        "detail_json": json.dumps(detail), "traces_json": json.dumps(result.traces),
    })
    return row


def result_public(row: dict, with_traces: bool = True) -> ResultPublic:
    """The API view of a stored result row (traces left out where a list shows many results)."""
    detail = json.loads(row.get("detail_json") or "{}")
    return ResultPublic(
        id=row["id"], status=row["status"], error=row["error"], method=row["method"], message=detail.get("message"),
        operating_point=OperatingPoint(torque_nm=row["torque_nm"], speed_rpm=row["speed_rpm"], udc_v=row["udc_v"]),
        harmonic_order=row["harmonic_order"], gamma_deg=row.get("gamma_deg"), delta_deg=row.get("delta_deg"),
        theta_cos=row.get("theta_cos"), theta_sin=row.get("theta_sin"), residual=detail.get("residual"),
        uncompensated=detail.get("uncompensated"), suppression_db=row.get("suppression_db"),
        target_db=row.get("target_db"), noise_floor_db=row.get("noise_floor_db"), plant_time_s=row.get("plant_time_s"),
        windows_used=row.get("windows_used"), windows_discarded=detail.get("windows_discarded"),
        s_model=detail.get("s_model"), s_measured=detail.get("s_measured"), details=detail.get("details"),
        options=json.loads(row["options_json"]), bench_identity=row["bench_identity"],
        software_version=row["software_version"], started_at=row["started_at"], finished_at=row["finished_at"],
        traces=json.loads(row.get("traces_json") or "{}") if with_traces else {}, recording=_recording(row))


def _recording(row: dict) -> RecordingPublic | None:
    record = recording_record(row)
    if record is None:
        return None
    why = unavailable_reason(record)
    fmt = record.get("format", "mf4")
    return RecordingPublic(available=why is None, format=fmt, error=why,
                           url=f"/api/v1/results/{row['id']}/recording?format={fmt}" if why is None else None,
                           **{k: record.get(k) for k in ("bytes", "samples", "stale_samples", "setpoints",
                                                         "sample_rate_hz")})


# --- jobs, sweeps, maps -----------------------------------------------------------------------------
def job_public(storage: Storage, job: dict) -> JobPublic:
    row = storage.get_result(job["result_id"]) if job.get("result_id") else None
    validation = storage.validation_of_job(job["id"]) if job["kind"] == "validation" else None
    result = result_public(row) if row else None
    if job["kind"] == "refinement" and job["sweep_id"] is not None:
        result = refinement_public(storage, storage.get_sweep(job["sweep_id"]))
    return JobPublic(id=job["id"], kind=job["kind"], state=job["state"], request=json.loads(job["request_json"]),
                     sweep_id=job["sweep_id"], error=job["error"], created_at=job["created_at"],
                     started_at=job["started_at"], finished_at=job["finished_at"], result=result,
                     validation=validation_public(validation) if validation else None)


def validation_summary_public(row: dict) -> ValidationSummaryPublic:
    summary = json.loads(row["summary_json"])
    return ValidationSummaryPublic(id=row["id"], job_id=row["job_id"], map_id=row["map_id"], state=row["state"],
                                   error=row["error"], finished_at=row["finished_at"],
                                   download=json.loads(row["download_json"]), **summary)


def validation_public(row: dict) -> ValidationPublic:
    return ValidationPublic(**validation_summary_public(row).model_dump(), harmonic_order=row["harmonic_order"],
                            options=json.loads(row["options_json"]), bench_identity=row["bench_identity"],
                            software_version=row["software_version"], started_at=row["started_at"],
                            cells=json.loads(row["cells_json"]))


def sweep_public(storage: Storage, sweep: dict, with_points: bool = False) -> SweepPublic:
    points = None
    if with_points:
        points = [SweepPointPublic(operating_point=OperatingPoint(torque_nm=r["torque_nm"], speed_rpm=r["speed_rpm"],
                                                                  udc_v=r["udc_v"]),
                                   state=r["status"], error=r["error"], result=result_public(r, with_traces=False))
                  for r in storage.sweep_results(sweep["id"])]
    outcome = storage.sweep_outcome(sweep["id"])
    return SweepPublic(
        id=sweep["id"], state=sweep["state"], method=sweep["method"], harmonic_order=sweep["harmonic_order"],
        grid=json.loads(sweep["grid_json"]), options=json.loads(sweep["options_json"]),
        progress={"done": sweep["done_points"], "failed": sweep["failed_points"], "total": sweep["total_points"],
                  **outcome["counts"]},
        plant_time_s=outcome["plant_time_s"], map_id=sweep["map_id"], error=sweep["error"],
        pause_reason=sweep.get("pause_reason"), bench_identity=sweep["bench_identity"],
        software_version=sweep["software_version"], created_at=sweep["created_at"], started_at=sweep["started_at"],
        finished_at=sweep["finished_at"], schedule_id=sweep.get("schedule_id"), points=points,
        kind=sweep.get("kind") or "sweep",
        refinement=refinement_public(storage, sweep) if sweep.get("kind") == "refinement" else None)


def refinement_public(storage: Storage, sweep: dict) -> RefinementPublic:
    state = json.loads(sweep["refinement_json"])
    latest = storage.latest_validation(state["current_map_id"])
    rounds = [RefinementRoundPublic(**r) for r in state["rounds"]]
    holds = bool(rounds) and rounds[-1].below_target == 0 and rounds[-1].map_id == state["current_map_id"]
    return RefinementPublic(refinement_id=sweep["id"], source_map_id=sweep["source_map_id"],
                            map_id=state["current_map_id"], state=sweep["state"], phase=state["phase"],
                            target_db=state["target_db"], max_cells=state["max_cells"],
                            cells_added=state["cells_added"], holds=holds, stopped=state.get("stopped"),
                            rounds=rounds, validation=validation_summary_public(latest) if latest else None)


def map_public(storage: Storage, map_id: int, smooth: bool = False) -> MapPublic | None:
    """The stored map with each ok cell's quality; `smooth`: the view whose outlier cells carry their
    neighbours' fit instead of the measured theta (marked `smoothed`, the stored map is not changed)."""
    row = storage.get_map(map_id)
    if row is None:
        return None
    cells = []
    for c in row["cells"]:
        status = c["status"] or "missing"
        ok = status == "ok"
        cell = MapCellPublic(
            torque_nm=c["torque_nm"], speed_rpm=c["speed_rpm"], udc_v=c["udc_v"], status=status,
            result_id=c["result_id"], gamma_deg=c["gamma_deg"] if ok else None, delta_deg=c["delta_deg"] if ok else None,
            theta_cos=c["theta_cos"] if ok else None, theta_sin=c["theta_sin"] if ok else None,
            suppression_db=c["suppression_db"], target_db=c.get("target_db"), noise_floor_db=c.get("noise_floor_db"),
            error=c["error"])
        if not ok and c.get("fill_theta_cos") is not None:      # the fill rule's entry (service/maps/fill.py)
            cell.theta_cos, cell.theta_sin = c["fill_theta_cos"], c["fill_theta_sin"]
            cell.gamma_deg, cell.delta_deg = (math.degrees(v) for v in gamma_delta(cell.theta_cos, cell.theta_sin))
            cell.filled, cell.fill_source = True, c["fill_source"]
        cells.append(cell)
    counts = {status: 0 for status in CELL_STATUSES}
    for c in cells:
        counts[c.status] = counts.get(c.status, 0) + 1
    axes = json.loads(row["axes_json"])
    validation = storage.latest_validation(map_id)
    quality = map_quality.assess([c.model_dump() for c in cells], axes)
    smoothed = {}
    if smooth:
        smoothed = map_quality.smoothing(quality, map_id, {map_quality.cell_key(c.model_dump()): c.result_id
                                                           for c in cells})
        for c in cells:
            key = map_quality.cell_key(c.model_dump())
            if key in smoothed:
                (c.theta_cos, c.theta_sin), c.smoothed_from = smoothed[key]
                c.outlier_reason, c.quality = quality.cells[key].reason, "smoothed"
                c.gamma_deg, c.delta_deg = (math.degrees(v) for v in gamma_delta(c.theta_cos, c.theta_sin))
                c.suppression_db = None        # measured at the replaced theta, not at this one
        quality = map_quality.assess([c.model_dump() for c in cells], axes)
    for c in cells:
        q = quality.cells.get(map_quality.cell_key(c.model_dump()))
        if q is not None and c.quality is None:
            c.quality, c.outlier_reason = q.quality, q.reason
    summary = MapQualityPublic(
        consistent=sum(1 for c in cells if c.quality == "consistent"),
        outliers=sum(1 for c in cells if c.quality == "outlier"),
        unchecked=sum(1 for c in cells if c.quality == "unchecked"), smoothed=len(smoothed),
        outlier_factor=map_quality.OUTLIER_FACTOR, min_step_deg=map_quality.MIN_STEP_DEG,
        gradient_deg_per_unit={a: None if g is None else math.degrees(g) for a, g in quality.gradient_rad_per_unit.items()})
    return MapPublic(id=row["id"], sweep_id=row["sweep_id"], harmonic_order=row["harmonic_order"], method=row["method"],
                     bench_identity=row["bench_identity"], software_version=row["software_version"],
                     created_at=row["created_at"], axes=axes, status_counts=counts, cells=cells,
                     filled_cells=sum(1 for c in cells if c.filled), refined_from=row.get("refined_from"),
                     provenance=json.loads(row["provenance_json"]) if row.get("provenance_json") else None,
                     quality=summary, smoothed=smooth,
                     validation=validation_summary_public(validation) if validation else None)


def schedule_public(storage: Storage, row: dict, now, next_count: int = 5, run_count: int = 20) -> SchedulePublic:
    """`now`: the scheduler's clock (aware), from which next_runs are counted."""
    zone = ZoneInfo(row["timezone"])

    def local(text: str) -> str:
        return iso(datetime.fromisoformat(text).astimezone(zone))
    upcoming = next_runs(row["cron"], zone, now, next_count) if row["enabled"] else []
    runs = [ScheduleRunPublic(id=r["id"], due_at=local(r["due_at"]), fired_at=local(r["fired_at"]), outcome=r["outcome"],
                              sweep_id=r["sweep_id"], sweep_state=r["sweep_state"], note=r["note"])
            for r in storage.schedule_runs(row["id"], run_count)]
    return SchedulePublic(id=row["id"], name=row["name"], cron=row["cron"], timezone=row["timezone"],
                          sweep=json.loads(row["sweep_json"]), enabled=bool(row["enabled"]), created_at=local(row["created_at"]),
                          updated_at=local(row["updated_at"]), next_runs=[iso(t) for t in upcoming], runs=runs)


def map_summaries(storage: Storage, limit: int) -> list[MapSummaryPublic]:
    return [MapSummaryPublic(**row) for row in storage.list_maps(limit)]


class LutDownloadPublic(BaseModel):
    """What went into the drive (POST /maps/{id}/download, `ripplecal maps download`, a validation job)."""
    map_id: int = Field(description="the map the drive now holds (it reports it on 0x2001:4)")
    crc32: str = Field(description="CRC-32 (zlib) of the LUT image without its CRC field, as the drive read it "
                                   "back (0x2001:2): 0x and 8 hex digits")
    bytes: int = Field(description="size of the LUT image")
    cells: int = Field(description="cells of the map")
    valid_cells: int = Field(description="cells with status ok (VALID)")
    filled_cells: int = Field(0, description="cells not ok that went in with their fill (service/maps/fill.py); "
                              "the drive injects at ok and filled cells")
    fill: bool = Field(True, description="whether the fills were chosen for this download")
    interpolation: str = Field("cartesian", description="what the drive interpolates between cells: cartesian "
                               "(theta_cos, theta_sin) or polar (gamma, delta along the shortest arc)")
    format_version: int = Field(3, description="LUT image format version (drivers/lut_image.py)")
    harmonic_order: int
    forced: bool = Field(description="true when a map with holes (cells that inject nothing) went in on force=true")
