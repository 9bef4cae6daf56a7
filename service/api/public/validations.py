"""A map's validation in the drive's LUT mode: every cell, and the figures a summary shows."""

from __future__ import annotations

from typing import Any, Mapping

from pydantic import BaseModel, Field

from service.api.public.results import PhasorPublic
from service.model.operating_point import OperatingPoint


class OrderFigurePublic(BaseModel):
    """A further order of a map of several orders at a validation point, judged from the point's own windows."""

    order: int
    suppression_db: float | None = None
    above_floor_db: float | None = None
    holds: bool | None = None
    at_noise_floor: bool | None = None
    uncompensated: PhasorPublic | None = None
    residual: PhasorPublic | None = None


class OrderSummaryPublic(BaseModel):
    """An order's figures over a validation's grid and midpoint points (order null: the map's own)."""

    order: int | None
    points: int
    held: int
    median_db: float | None = None
    min_db: float | None = None


class ValidationCellPublic(BaseModel):
    """One point of a validation: a grid point or an untrained midpoint, measured in the drive's LUT mode."""

    operating_point: OperatingPoint
    kind: str = Field(
        description="grid (a trained cell) | midpoint (between neighbouring grid values: interpolated) | runup (a "
        "speed bin of the run-ups without and with the LUT at one torque: service/runs/runup_validation.py)"
    )
    status: str = Field(description="measured | failed (error says why) | not_measured (the run stopped first)")
    error: str | None = None
    suppression_db: float | None = Field(None, description="20 log10(|uncompensated| / |residual|), only if measured")
    uncompensated: PhasorPublic | None = Field(None, description="injection off")
    residual: PhasorPublic | None = Field(None, description="the drive's own LUT feedforward (injection mode 2)")
    noise_floor_db: float | None = Field(None, description="rms noise phasor of the LUT window against |uncompensated|")
    above_floor_db: float | None = Field(None, description="the uncompensated order over the noise floor, dB")
    holds: bool | None = Field(
        None, description="suppression_db >= the validation's target_db (run-up bins: or below the range's floor rule)"
    )
    reason: str | None = Field(None, description="why a judged point does not hold (run-up bins: or how it holds)")
    uncompensated_fs: float | None = Field(None, description="run-up bins: |order| without the LUT, full scale")
    residual_fs: float | None = Field(None, description="run-up bins: |order| with the LUT, full scale")
    at_noise_floor: bool | None = Field(
        None, description="the residual is within 3 noise rms of zero: suppression_db is a lower bound"
    )
    plant_time_s: float | None = Field(None, description="the point's measurements (both windows), plant seconds")
    settle_plant_s: float | None = Field(
        None, description="the point's settling, from the move's effect to steady (DAQ clock), plant seconds"
    )
    no_injection: bool | None = Field(
        None,
        description="the drive's LUT injects nothing here (a cell turned off, LUT flag 3, weighs at the point or over "
        "its whole run-up bin): the figure is no compensation by construction, never harm",
    )
    bin_rpm: float | None = Field(None, description="run-up bins: the bin's width, rpm (speed_rpm its centre)")
    reused: bool | None = Field(
        None,
        description="taken from the validation before (a refinement's guard round): the drive's LUT is the same here "
        "as then; plant_time_s and settle_plant_s 0",
    )
    speed_rpm_measured: float | None = None
    harmonic_frequency_hz: float | None = None
    map_cell_status: str | None = Field(None, description="grid points: the map cell's status")
    map_cell_filled: bool | None = Field(
        None, description="grid points: the cell went into the LUT with its fill (not ok, service/maps/fill.py)"
    )
    bench_time_s: dict[str, float] | None = Field(
        None, description="wall seconds of the point by what they were spent on: move, accounting, settle, measurement"
    )
    orders: list[OrderFigurePublic] | None = Field(
        None, description="a map of several orders: every further order's figure at this point (the first's are above)"
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
    runup: dict[str, Any] | None = Field(None, description="the run-up bins, as grid and midpoint")
    worst: dict[str, Any] | None = None
    plant_time_s: float = Field(
        description="bench time: every point's settling and measurements and the run-up pairs, plant seconds (what a "
        "bench pays at speedup 1, but for the download and the moves' commands)"
    )
    settle_plant_s: float | None = Field(None, description="of plant_time_s, the points' settling")
    points: int | None = Field(None, description="judged points: grid, midpoints and run-up bins measured")
    held: int | None = Field(None, description="of them, how many hold (holds)")
    median_db: float | None = None
    min_db: float | None = None
    torques_run_up: list[float] | None = Field(None, description="the torques the LUT was judged along run-ups at")
    runup_plant_time_s: float | None = Field(None, description="plant seconds of the run-up pairs (in plant_time_s)")
    runups_reused: int | None = Field(
        None, description="uncompensated run-ups reused from an earlier validation of the same refinement"
    )
    orders: list[OrderSummaryPublic] | None = Field(
        None, description="a map of several orders: each order's points, held, median and minimum (grid and midpoints)"
    )
    no_injection: int | None = Field(
        None, description="judged points where the drive's LUT injects nothing (cells turned off): never harm"
    )
    items_reused: int | None = Field(
        None,
        description="points and run-up pairs taken from the validation before, where a guard round left the LUT "
        "the same (service/runs/refinement.py touched_by)",
    )


class ValidationPublic(ValidationSummaryPublic):
    harmonic_order: int
    options: dict[str, Any]
    bench_identity: str
    software_version: str
    started_at: str
    cells: list[ValidationCellPublic]


def validation_summary_public(row: Mapping[str, Any]) -> ValidationSummaryPublic:
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


def validation_public(row: Mapping[str, Any]) -> ValidationPublic:
    return ValidationPublic(
        **validation_summary_public(row).model_dump(),
        harmonic_order=row["harmonic_order"],
        options=row["options"],
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        started_at=row["started_at"],
        cells=row["cells"],
    )
