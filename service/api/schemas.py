"""Request/response schemas (Create / Public families)."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from service.identification.registry import METHODS
from service.operating_point import OperatingPoint
from service.plans import Grid


MethodName = Literal[tuple(METHODS)]


class IdentificationCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"operating_point": {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}, "method": "adaptive", "options": {}}]})
    operating_point: OperatingPoint
    method: MethodName = "adaptive"
    options: dict[str, Any] = Field(default_factory=dict)


class SweepCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"grid": {"torque_nm": [1, 2.5, 4], "speed_rpm": [1000, 2000, 2500], "udc_v": [12]}, "method": "adaptive"}]})
    grid: Grid
    method: MethodName = "adaptive"
    options: dict[str, Any] = Field(default_factory=dict)
    confirm_large: bool = Field(False, description="required for a grid above safety.max_sweep_points_unconfirmed "
                                                   "points (a run of hours is started on purpose)")


class ErrorPublic(BaseModel):
    """Every refusal except 422 (which lists one item per field, see HTTPValidationError)."""
    detail: str = Field(..., description="what was refused and why")


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
    result: dict[str, Any] | None = None


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
    points: list[dict[str, Any]] | None = None
