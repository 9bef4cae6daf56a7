"""The public shapes (the Public schema family) in one place, at the API's edge: routes, SSE events
and the CLI answer with these models, so /docs shows every field. Each is built from what the layers
below keep: a result from its row (service/store/result_rows.py makes the row), a map from its view
(service/maps/view.py), jobs, sweeps, validations and schedules from their rows. No module below the
API imports this one.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Protocol
from zoneinfo import ZoneInfo

from pydantic import BaseModel, Field

from service.maps.compare import ComplexGain
from service.maps.view import MapView, map_view
from service.model.operating_point import OperatingPoint
from service.runs.schedules import iso, next_runs
from service.store.recordings import recording_record, unavailable_reason


class PhasorPublic(BaseModel):
    a_c: float = Field(description="(2/N) sum(alpha cos(h phi_e)), sensor full scale")
    a_s: float = Field(description="(2/N) sum(alpha sin(h phi_e)), sensor full scale")
    amplitude: float


class RecordingPublic(BaseModel):
    """The raw recording of one identification (DAQ samples and theta setpoints, MF4)."""

    available: bool = Field(description="the file can be downloaded (url)")
    format: str = Field("mf4", description="mf4: ASAM MDF 4.10")
    url: str | None = Field(None, description="GET it here while available")
    bytes: int | None = None
    samples: int | None = Field(
        None,
        description="DAQ samples in the file: those counted in plant_time_s "
        "(samples = plant_time_s x sample_rate_hz when the DAQ lost none)",
    )
    stale_samples: int | None = Field(
        None, description="samples read before a setpoint took effect: counted, not in the file"
    )
    setpoints: int | None = Field(None, description="theta setpoints, each with the sample at which it took effect")
    sample_rate_hz: float | None = None
    error: str | None = Field(
        None, description="why it is not available: the write failed (and why), or retention deleted it"
    )


class ResultPublic(BaseModel):
    """One identification at one operating point, self-describing (statuses: docs/conventions.md, Statuses)."""

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
    noise_floor_db: float | None = Field(
        None, description="rms noise phasor of the final window against |uncompensated|"
    )
    torque_actual_nm: float | None = Field(
        None,
        description="the torque the point ran at: the drive's torque actual, mean over the measurement, Nm "
        "(a result whose torque left its command beyond safety.torque_tolerance_* is never ok)",
    )
    plant_time_s: float | None = Field(None, description="DAQ samples / rate, counted from each setpoint's effect")
    windows_used: int | None = None
    windows_discarded: int | None = None
    s_model: ComplexGain | None = None
    s_measured: ComplexGain | None = None
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
    bench: str | None = Field(None, description="the bench it runs on")
    waiting_for: str | None = Field(
        None, description="queued for another bench: which, and whether it is online (e.g. not seen since ...)"
    )
    request: dict[str, Any]
    sweep_id: int | None = None
    error: str | None = None
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    result: "ResultPublic | RefinementPublic | None" = Field(
        None,
        description="kind identification: the result; kind "
        "refinement: the refined map, its rounds, the cells added "
        "and the final validation",
    )
    validation: "ValidationPublic | None" = Field(
        None, description="kind validation: the map's LUT measured in the drive's LUT mode, every cell"
    )


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
    bench: str | None = Field(None, description="the bench it runs on")
    waiting_for: str | None = Field(None, description="queued for another bench: which, and whether it is online")
    control_request: str | None = Field(
        None, description="pause | resume | cancel asked at another service, for its bench's service to act on"
    )
    control_note: str | None = Field(None, description="a control request its bench's service refused, and why")
    method: str
    harmonic_order: int
    grid: dict[str, Any]
    options: dict[str, Any]
    progress: dict[str, int] = Field(
        description="done, failed, total, and the current results per status: ok, below_target, no_authority, failed"
    )
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
    outcome: str = Field(
        description="started (the bench was free) | queued (behind a run in progress) | skipped "
        "(this schedule's previous sweep still waits) | missed (the service was down "
        "longer than schedules.missed_grace_s) | failed (the sweep was refused)"
    )
    sweep_id: int | None = None
    sweep_state: str | None = Field(None, description="the state of that sweep now")
    note: str | None = None


class BenchPublic(BaseModel):
    """A bench of the lab: one service per bench, all on one database (service/runs/lab.py)."""

    name: str
    state: str = Field(description="idle | busy | fault | disconnected | starting | stopped | unknown (never seen)")
    online: bool = Field(description="its service renewed its row within the last few seconds")
    seen: str = Field(description="online | not seen since ... | stopped since ... | never seen")
    last_seen: str | None = Field(None, description="UTC ISO 8601")
    busy: bool
    running: str | None = Field(None, description="what it runs now, e.g. sweep 12")
    queue: int = Field(description="jobs queued for it")
    software_version: str | None = None
    host: str | None = None
    port: int | None = None
    own: bool = Field(description="the bench of the service that answers")


class SchedulePublic(BaseModel):
    id: int
    name: str
    bench: str | None = Field(None, description="the bench whose service fires it")
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
    at_noise_floor: bool | None = Field(
        None, description="the residual is within 3 noise rms of zero: suppression_db is a lower bound"
    )
    plant_time_s: float | None = None
    speed_rpm_measured: float | None = None
    harmonic_frequency_hz: float | None = None
    map_cell_status: str | None = Field(None, description="grid points: the map cell's status")
    map_cell_filled: bool | None = Field(
        None, description="grid points: the cell went into the LUT with its fill (not ok, service/maps/fill.py)"
    )
    bench_time_s: dict[str, float] | None = Field(
        None, description="wall seconds of the point by what they were spent on: move, accounting, settle, measurement"
    )


class ValidationSummaryPublic(BaseModel):
    """A validation's figures: per kind (grid, midpoint) the cells, how many were measured, failed or
    not measured, and the median / minimum suppression of the measured ones (dB); the worst cell."""

    id: int
    job_id: int
    map_id: int
    state: str = Field(
        description="running (stored as it measures) | done | failed (interlock, error or the "
        "service stopped: see error) | cancelled"
    )
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


JobPublic.model_rebuild()  # their `validation` fields name the models defined above
RefinementPublic.model_rebuild()
SweepPublic.model_rebuild()


class MapPublic(MapView):
    """GET /maps/{id}: the map (service/maps/view.py) with its latest validation."""

    validation: ValidationSummaryPublic | None = Field(
        None, description="the latest validation in the drive's LUT mode (cells: GET /maps/{id}/validation)"
    )


# --- results: row -> public (service/store/result_rows.py makes the row) -----------------------------
def result_public(row: dict, with_traces: bool = True) -> ResultPublic:
    """The API view of a stored result row (traces left out where a list shows many results)."""
    detail = row.get("detail") or {}
    return ResultPublic(
        id=row["id"],
        status=row["status"],
        error=row["error"],
        method=row["method"],
        message=detail.get("message"),
        operating_point=OperatingPoint(torque_nm=row["torque_nm"], speed_rpm=row["speed_rpm"], udc_v=row["udc_v"]),
        harmonic_order=row["harmonic_order"],
        gamma_deg=row.get("gamma_deg"),
        delta_deg=row.get("delta_deg"),
        theta_cos=row.get("theta_cos"),
        theta_sin=row.get("theta_sin"),
        residual=detail.get("residual"),
        uncompensated=detail.get("uncompensated"),
        suppression_db=row.get("suppression_db"),
        target_db=row.get("target_db"),
        noise_floor_db=row.get("noise_floor_db"),
        torque_actual_nm=row.get("torque_actual_nm"),
        plant_time_s=row.get("plant_time_s"),
        windows_used=row.get("windows_used"),
        windows_discarded=detail.get("windows_discarded"),
        s_model=detail.get("s_model"),
        s_measured=detail.get("s_measured"),
        details=detail.get("details"),
        options=row["options"],
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        traces=(row.get("traces") or {}) if with_traces else {},
        recording=_recording(row),
    )


def _recording(row: dict) -> RecordingPublic | None:
    record = recording_record(row)
    if record is None:
        return None
    why = unavailable_reason(record)
    fmt = record.get("format", "mf4")
    return RecordingPublic(
        available=why is None,
        format=fmt,
        error=why,
        url=f"/api/v1/results/{row['id']}/recording?format={fmt}" if why is None else None,
        **{k: record.get(k) for k in ("bytes", "samples", "stale_samples", "setpoints", "sample_rate_hz")},
    )


# --- jobs, sweeps, maps -----------------------------------------------------------------------------
class Records(Protocol):
    """What the public shapes are built from: the service layer's reads (CalibrationService; a Storage
    has the same methods, so tools and tests may pass one)."""

    def get_result(self, result_id: int) -> dict | None: ...
    def validation_of_job(self, job_id: int) -> dict | None: ...
    def get_sweep(self, sweep_id: int) -> dict | None: ...
    def sweep_results(self, sweep_id: int) -> list[dict]: ...
    def sweep_outcome(self, sweep_id: int) -> dict: ...
    def get_map(self, map_id: int) -> dict | None: ...
    def list_maps(self, limit: int) -> list[dict]: ...
    def latest_validation(self, map_id: int) -> dict | None: ...
    def schedule_runs(self, schedule_id: int, limit: int) -> list[dict]: ...


def _waiting_for(records: Records, row: dict) -> str | None:
    """A queued job or sweep of another bench: what it waits for (only the service layer knows the lab)."""
    waiting = getattr(records, "waiting_for", None)
    if row["state"] != "queued" or waiting is None:
        return None
    return waiting(row.get("bench"))


def bench_public(row: dict) -> BenchPublic:
    return BenchPublic(**row)


def job_public(records: Records, job: dict) -> JobPublic:
    row = records.get_result(job["result_id"]) if job.get("result_id") else None
    validation = records.validation_of_job(job["id"]) if job["kind"] == "validation" else None
    result = result_public(row) if row else None
    if job["kind"] == "refinement" and job["sweep_id"] is not None:
        result = refinement_public(records, records.get_sweep(job["sweep_id"]))
    return JobPublic(
        id=job["id"],
        kind=job["kind"],
        state=job["state"],
        bench=job.get("bench"),
        waiting_for=_waiting_for(records, job),
        request=job["request"],
        sweep_id=job["sweep_id"],
        error=job["error"],
        created_at=job["created_at"],
        started_at=job["started_at"],
        finished_at=job["finished_at"],
        result=result,
        validation=validation_public(validation) if validation else None,
    )


def validation_summary_public(row: dict) -> ValidationSummaryPublic:
    summary = row["summary"]
    return ValidationSummaryPublic(
        id=row["id"],
        job_id=row["job_id"],
        map_id=row["map_id"],
        state=row["state"],
        error=row["error"],
        finished_at=row["finished_at"],
        download=row["download"],
        **summary,
    )


def validation_public(row: dict) -> ValidationPublic:
    return ValidationPublic(
        **validation_summary_public(row).model_dump(),
        harmonic_order=row["harmonic_order"],
        options=row["options"],
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        started_at=row["started_at"],
        cells=row["cells"],
    )


def sweep_public(records: Records, sweep: dict, with_points: bool = False) -> SweepPublic:
    points = None
    if with_points:
        points = [
            SweepPointPublic(
                operating_point=OperatingPoint(torque_nm=r["torque_nm"], speed_rpm=r["speed_rpm"], udc_v=r["udc_v"]),
                state=r["status"],
                error=r["error"],
                result=result_public(r, with_traces=False),
            )
            for r in records.sweep_results(sweep["id"])
        ]
    outcome = records.sweep_outcome(sweep["id"])
    return SweepPublic(
        id=sweep["id"],
        state=sweep["state"],
        bench=sweep.get("bench"),
        waiting_for=_waiting_for(records, sweep),
        control_request=sweep.get("control_request"),
        control_note=sweep.get("control_note"),
        method=sweep["method"],
        harmonic_order=sweep["harmonic_order"],
        grid=sweep["grid"],
        options=sweep["options"],
        progress={
            "done": sweep["done_points"],
            "failed": sweep["failed_points"],
            "total": sweep["total_points"],
            **outcome["counts"],
        },
        plant_time_s=outcome["plant_time_s"],
        map_id=sweep["map_id"],
        error=sweep["error"],
        pause_reason=sweep.get("pause_reason"),
        bench_identity=sweep["bench_identity"],
        software_version=sweep["software_version"],
        created_at=sweep["created_at"],
        started_at=sweep["started_at"],
        finished_at=sweep["finished_at"],
        schedule_id=sweep.get("schedule_id"),
        points=points,
        kind=sweep.get("kind") or "sweep",
        refinement=refinement_public(records, sweep) if sweep.get("kind") == "refinement" else None,
    )


def refinement_public(records: Records, sweep: dict) -> RefinementPublic:
    state = sweep["refinement"]
    latest = records.latest_validation(state["current_map_id"])
    rounds = [RefinementRoundPublic(**r) for r in state["rounds"]]
    holds = bool(rounds) and rounds[-1].below_target == 0 and rounds[-1].map_id == state["current_map_id"]
    return RefinementPublic(
        refinement_id=sweep["id"],
        source_map_id=sweep["source_map_id"],
        map_id=state["current_map_id"],
        state=sweep["state"],
        phase=state["phase"],
        target_db=state["target_db"],
        max_cells=state["max_cells"],
        cells_added=state["cells_added"],
        holds=holds,
        stopped=state.get("stopped"),
        rounds=rounds,
        validation=validation_summary_public(latest) if latest else None,
    )


def schedule_public(records: Records, row: dict, now, next_count: int = 5, run_count: int = 20) -> SchedulePublic:
    """`now`: the scheduler's clock (aware), from which next_runs are counted."""
    zone = ZoneInfo(row["timezone"])

    def local(text: str) -> str:
        return iso(datetime.fromisoformat(text).astimezone(zone))

    upcoming = next_runs(row["cron"], zone, now, next_count) if row["enabled"] else []
    runs = [
        ScheduleRunPublic(
            id=r["id"],
            due_at=local(r["due_at"]),
            fired_at=local(r["fired_at"]),
            outcome=r["outcome"],
            sweep_id=r["sweep_id"],
            sweep_state=r["sweep_state"],
            note=r["note"],
        )
        for r in records.schedule_runs(row["id"], run_count)
    ]
    return SchedulePublic(
        id=row["id"],
        name=row["name"],
        bench=row.get("bench"),
        cron=row["cron"],
        timezone=row["timezone"],
        sweep=row["sweep"],
        enabled=bool(row["enabled"]),
        created_at=local(row["created_at"]),
        updated_at=local(row["updated_at"]),
        next_runs=[iso(t) for t in upcoming],
        runs=runs,
    )


def map_public(records: Records, map_id: int, smooth: bool = False) -> MapPublic | None:
    view = map_view(records, map_id, smooth)
    if view is None:
        return None
    validation = records.latest_validation(map_id)
    return MapPublic(**dict(view), validation=validation_summary_public(validation) if validation else None)


def map_summaries(records: Records, limit: int) -> list[MapSummaryPublic]:
    return [MapSummaryPublic(**row) for row in records.list_maps(limit)]
