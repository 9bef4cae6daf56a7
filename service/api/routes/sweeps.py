"""Sweeps: an operating-point grid measured point by point, paused, resumed, cancelled."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, HTTPException, Query, status

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.sweeps import SweepPublic, sweep_public
from service.api.refusals import refusals_at
from service.api.schemas import SweepCreate
from service.runs.lab import is_own_bench
from service.runs.plans import (
    SweepPreview,
    check_orders,
    check_sweep_size,
    plan_grid,
    preview_sweep,
)

router = APIRouter(prefix="/api/v1", tags=["sweeps"])


@router.post(
    "/sweeps",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=SweepPublic,
    responses=error_responses(400, 401, 403, 409, 413),
    dependencies=[
        refusals_at(
            ["body", "grid"],
            regime=["body", "regime"],
            confirm_large=["body", "confirm_large"],
            orders=["body", "orders"],
        )
    ],
)
def create_sweep(body: SweepCreate, service: ServiceDep, _: OperatorDep) -> SweepPublic:
    # the size that counts is the planned grid's (speeds placed around the onset included; another
    # bench's grid as given: its placement needs that bench's machine)
    own = is_own_bench(body.bench, service.settings.bench_name)
    if own:  # the grid's values against this bench's limits: the engine's submit, first of all it checks
        check_orders(body.orders, service.settings.identification.harmonic_order)
    planned = plan_grid(body.grid, body.regime, service.settings) if own else None  # the one plan: it travels
    check_sweep_size(planned.grid if planned else body.grid, body.confirm_large, service.settings.safety)
    sweep_id = service.engine.submit_sweep(
        body.grid, body.method, body.options, regime=body.regime, bench=body.bench, planned=planned
    )
    return sweep_public(service.records, service.seen_sweep(sweep_id), service=service)


@router.post("/sweeps/preview", response_model=SweepPreview, responses=error_responses(400, 413))
def preview_sweep_plan(body: SweepCreate, service: ServiceDep) -> SweepPreview:
    """The plan POST /sweeps would queue for this body, without queueing or moving anything (no token):
    the points in measuring order, the planned speed axis (values placed around the predicted
    field-weakening onset and why), the onset per torque and U_dc, what POST /sweeps would refuse (as a
    list, `accepted` false), and an estimate of the bench time."""
    return preview_sweep(
        body.grid, body.regime, body.method, body.options, body.confirm_large, service.settings, orders=body.orders
    )


@router.get("/sweeps", response_model=list[SweepPublic])
def list_sweeps(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[SweepPublic]:
    return [sweep_public(service.records, s, service=service) for s in service.seen_sweeps(limit)]


@router.get("/sweeps/{sweep_id}", response_model=SweepPublic, responses=error_responses(404))
def get_sweep(sweep_id: ResourceId, service: ServiceDep) -> SweepPublic:
    sweep = service.seen_sweep(sweep_id)
    if sweep is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"sweep {sweep_id} does not exist")
    return sweep_public(service.records, sweep, with_points=True, service=service)


@router.post("/sweeps/{sweep_id}/{action}", response_model=SweepPublic, responses=error_responses(401, 403, 404, 409))
def control_sweep(
    sweep_id: ResourceId, action: Literal["pause", "resume", "cancel"], service: ServiceDep, _: OperatorDep
) -> SweepPublic:
    service.control_sweep(sweep_id, action)
    return sweep_public(service.records, service.seen_sweep(sweep_id), service=service)
