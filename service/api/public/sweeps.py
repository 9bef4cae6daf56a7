"""A sweep (an operating-point grid measured point by point, or a refinement's) with its progress."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from pydantic import BaseModel, Field

from service.api.public.benches import queued_waiting_for
from service.api.public.refinements import RefinementPublic, refinement_public
from service.api.public.results import ResultPublic, result_public
from service.model.operating_point import OperatingPoint

if TYPE_CHECKING:
    from service.calibration_service import CalibrationService, Records


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
    orders: list[int] = Field(
        default_factory=list,
        description="the harmonic orders each point cancels (method probe-orders: options.orders), the run's first",
    )
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
    source_map_id: int | None = Field(None, description="kind refinement: the map it refines")
    refinement: RefinementPublic | None = None
    points: list[SweepPointPublic] | None = None


def sweep_orders(sweep: Mapping[str, Any]) -> list[int]:
    """The orders a sweep cancels: its own harmonic order, then any further ones its method's options name."""
    h = int(sweep["harmonic_order"])
    return [h, *(int(o) for o in (sweep.get("options") or {}).get("orders") or [] if int(o) != h)]


def sweep_public(
    records: Records, sweep: Mapping[str, Any], with_points: bool = False, service: CalibrationService | None = None
) -> SweepPublic:
    """`sweep`: as its run sees it where a service runs (CalibrationService.seen_sweep); `service`: for
    what a queued sweep waits for (None: the database alone, as the CLI reads it)."""
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
        waiting_for=queued_waiting_for(service, sweep),
        control_request=sweep.get("control_request"),
        control_note=sweep.get("control_note"),
        method=sweep["method"],
        harmonic_order=sweep["harmonic_order"],
        orders=sweep_orders(sweep),
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
        source_map_id=sweep.get("source_map_id"),
        refinement=refinement_public(records, sweep) if sweep.get("kind") == "refinement" else None,
    )
