"""The records the store hands out: one TypedDict per table, the JSON columns decoded (`grid_json`
is read as `grid`, service/store/storage/rows.py JSON_COLUMNS). The layers above read these and never a
JSON string; the API's public shapes are built from them at the edge (service/api/public.py).
tests/unit/test_records_schema.py holds each record to its table's columns on both engines."""

from __future__ import annotations

from typing import Any, TypedDict


class JobRecord(TypedDict):
    id: int
    kind: str  # identification | sweep | validation | refinement
    state: str  # queued | running | done | failed | cancelled (service/runs/states.py JOB_TRANSITIONS)
    request: dict[str, Any]
    sweep_id: int | None
    result_id: int | None
    error: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None
    bench: str | None  # the bench it is for (None: a row from before schema 9, migrations/0009_benches.sql)
    claimed_by: str | None  # the service instance that runs it (None: whichever serves `bench` takes it)
    updated_at: str | None  # the database's clock at the last write


class SweepRecord(TypedDict):
    id: int
    state: str  # service/runs/states.py SWEEP_TRANSITIONS
    method: str
    harmonic_order: int
    grid: dict[str, list[float]]
    options: dict[str, Any]
    total_points: int
    done_points: int
    failed_points: int
    map_id: int | None
    error: str | None
    bench_identity: str
    software_version: str
    created_at: str
    started_at: str | None
    finished_at: str | None
    pause_reason: str | None
    schedule_id: int | None
    kind: str  # sweep | refinement
    source_map_id: int | None
    refinement: dict[str, Any] | None  # a refinement's state (service/runs/refinement.py)
    bench: str | None  # as JobRecord's
    updated_at: str | None
    control_request: str | None  # pause | resume | cancel asked at another bench's service
    control_note: str | None  # what became of a control request it refused


class ResultRecord(TypedDict):
    id: int
    job_id: int | None
    sweep_id: int | None
    torque_nm: float
    speed_rpm: float
    udc_v: float
    harmonic_order: int
    method: str
    options: dict[str, Any]
    status: str  # ok | below_target | no_authority | failed
    error: str | None
    theta_cos: float | None  # rad
    theta_sin: float | None  # rad
    gamma_deg: float | None
    delta_deg: float | None
    residual_a_c: float | None  # fs
    residual_a_s: float | None
    uncompensated_a_c: float | None
    uncompensated_a_s: float | None
    suppression_db: float | None
    plant_time_s: float | None
    windows_used: int | None
    detail: dict[str, Any]  # message, phasors, S, details (service/store/result_rows.py)
    traces: dict[str, Any]
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str
    target_db: float | None
    noise_floor_db: float | None
    superseded_by: int | None
    recording: dict[str, Any] | None  # service/store/recordings/store.py
    torque_actual_nm: float | None  # the drive's torque actual, mean over the measurement (schema 10)


def bench_plant_s(row: ResultRecord) -> float:
    """Plant seconds a result held the bench, on the DAQ clock: the settling at its operating point (from the move's
    effect to steady, details.op_settle_plant_s) and its method's measurement (plant_time_s). What a bench pays at
    speedup 1 (the commands between them take milliseconds): a budget in bench time counts both."""
    details = (row.get("detail") or {}).get("details") or {}
    return float(row.get("plant_time_s") or 0.0) + float(details.get("op_settle_plant_s") or 0.0)


class MapCellRecord(TypedDict):
    """A map_cells row joined with its result's columns (Storage.get_map)."""

    torque_nm: float
    speed_rpm: float
    udc_v: float
    result_id: int | None
    status: str | None  # the result's; None: no result (a missing cell)
    theta_cos: float | None
    theta_sin: float | None
    gamma_deg: float | None
    delta_deg: float | None
    suppression_db: float | None
    target_db: float | None
    noise_floor_db: float | None
    error: str | None
    fill_theta_cos: float | None  # the fill rule's entry (service/maps/fill.py)
    fill_theta_sin: float | None
    fill_source: str | None
    injection_off: int  # 1: the drive injects nothing around this cell (LUT flag 3; schema 12)


class MapRecord(TypedDict):
    id: int
    sweep_id: int | None
    harmonic_order: int
    method: str
    axes: dict[str, list[float]]
    bench_identity: str
    software_version: str
    created_at: str
    refined_from: int | None
    provenance: dict[str, Any] | None
    orders: list[dict[str, Any]] | None  # further orders [{order, cells}] (migrations/0013), None: one order
    cells: list[MapCellRecord]  # joined: the map_cells rows


class MapSummaryRecord(TypedDict):
    """Some of a maps row's columns (Storage.list_maps)."""

    id: int
    sweep_id: int | None
    harmonic_order: int
    method: str
    created_at: str


class ValidationRecord(TypedDict):
    id: int
    map_id: int
    job_id: int
    state: str  # running | done | failed | cancelled
    error: str | None
    harmonic_order: int
    options: dict[str, Any]
    download: dict[str, Any]
    summary: dict[str, Any]
    cells: list[dict[str, Any]]
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str | None


class RunupRecord(TypedDict):
    """A run-up (service/runs/runup.py): its request, and its order analysis when done."""

    id: int
    job_id: int
    state: str  # done | failed | cancelled
    error: str | None
    request: dict[str, Any]
    result: dict[str, Any] | None  # the order analysis (service/runs/runup.py measure_runup)
    recording: dict[str, Any] | None  # its raw recording, as a result's (service/store/recordings/store.py)
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str


class ScheduleRecord(TypedDict):
    id: int
    name: str
    cron: str
    timezone: str
    sweep: dict[str, Any]  # the sweep each firing submits
    enabled: int
    created_at: str
    updated_at: str
    last_due_at: str
    deleted_at: str | None
    bench: str | None  # the bench its sweeps are for


class ScheduleRunRecord(TypedDict):
    id: int
    schedule_id: int
    due_at: str
    fired_at: str
    outcome: str  # started | queued | skipped | missed | failed
    sweep_id: int | None
    note: str | None
    sweep_state: str | None  # joined: its sweep's state (Storage.list_schedule_runs)
