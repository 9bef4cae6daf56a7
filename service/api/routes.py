"""Thin routes: validate, call the service layer, shape the answer."""
from __future__ import annotations

import asyncio
import json
import math
from typing import Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi.responses import PlainTextResponse, StreamingResponse
from pydantic import ValidationError

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses, validation_error
from service.api.schemas import IdentificationCreate, JobPublic, SweepCreate, SweepPublic
from service.bench import BenchError
from service.limits import LimitError
from service.engine import TransitionError
from service.events import format_sse
from service.identify import PlantTimeError, parse_options, public_result
from service.lut_export import EXPORT_FORMATS, export_map, lut_image
from service.maps import public_map
from service.plans import SweepTooLarge, check_sweep_size

router = APIRouter(prefix="/api/v1")


def _unprocessable(*errors: dict[str, Any]) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, list(errors))


def _non_finite(options: dict[str, Any]) -> list[tuple[list, float]]:
    """(path, value) of every NaN / inf anywhere in the options (Python's json parser accepts them)."""
    found, stack = [], [([], options)]
    while stack:                        # iterative: nesting depth is the client's choice
        path, node = stack.pop()
        if isinstance(node, float) and not math.isfinite(node):
            found.append((path, node))
        elif isinstance(node, dict):
            stack += [([*path, k], v) for k, v in node.items()]
        elif isinstance(node, list):
            stack += [([*path, i], v) for i, v in enumerate(node)]
    return found


def _options(method: str, options: dict[str, Any]):
    """The method's option model, or a 422 naming options.<field>. The option models bound their
    fields; whatever else validating them raises (a bound missed) is still the request's fault."""
    if bad := _non_finite(options):
        raise _unprocessable(*(validation_error(["body", "options", *path], f"must be a finite number, got {value}",
                                                "finite_number") for path, value in bad))
    try:
        return parse_options(method, options)
    except ValidationError as exc:
        raise _unprocessable(*(validation_error(["body", "options", *e["loc"]], e["msg"], e["type"])
                               for e in exc.errors())) from None
    except (ValueError, TypeError, OverflowError, MemoryError, RecursionError) as exc:
        loc = ["body", "options", *list(options)[:1]] if len(options) == 1 else ["body", "options"]
        raise _unprocessable(validation_error(
            loc, f"{method} options {sorted(options)} cannot be used: {type(exc).__name__}: {exc}")) from None


def _limit_error(exc: LimitError, where: list[str]) -> HTTPException:
    """The bench's safety limits refused a setpoint: one 422 item per operating-point field at fault."""
    if not exc.problems:
        return _unprocessable(validation_error(where, str(exc), "value_error.bench_limits"))
    return _unprocessable(*(validation_error([*where, field], msg, "value_error.bench_limits")
                            for field, msg in exc.problems))


def _job_public(service, job: dict) -> JobPublic:
    result = None
    if job.get("result_id"):
        row = service.storage.get_result(job["result_id"])
        result = public_result(row) if row else None
    return JobPublic(id=job["id"], kind=job["kind"], state=job["state"], request=json.loads(job["request_json"]),
                     sweep_id=job["sweep_id"], error=job["error"], created_at=job["created_at"],
                     started_at=job["started_at"], finished_at=job["finished_at"], result=result)


def _sweep_public(service, sweep: dict, with_points: bool = False) -> SweepPublic:
    points = None
    if with_points:
        points = [{"operating_point": {"torque_nm": r["torque_nm"], "speed_rpm": r["speed_rpm"], "udc_v": r["udc_v"]},
                   "state": r["status"], "error": r["error"], "result": public_result({**r, "traces_json": "{}"})}
                  for r in service.storage.sweep_results(sweep["id"])]
    outcome = service.storage.sweep_outcome(sweep["id"])
    return SweepPublic(
        id=sweep["id"], state=sweep["state"], method=sweep["method"], harmonic_order=sweep["harmonic_order"],
        grid=json.loads(sweep["grid_json"]), options=json.loads(sweep["options_json"]),
        progress={"done": sweep["done_points"], "failed": sweep["failed_points"], "total": sweep["total_points"],
                  **outcome["counts"]},
        plant_time_s=outcome["plant_time_s"],
        map_id=sweep["map_id"], error=sweep["error"], pause_reason=sweep.get("pause_reason"), bench_identity=sweep["bench_identity"],
        software_version=sweep["software_version"], created_at=sweep["created_at"], started_at=sweep["started_at"],
        finished_at=sweep["finished_at"], points=points)


# --- bench --------------------------------------------------------------------------------------------
@router.get("/bench/status")
def bench_status(service: ServiceDep) -> dict:
    return service.bench.status()


@router.get("/version")
def version(service: ServiceDep) -> dict:
    return {"software_version": service.version, "bench": service.bench.identity}


# --- identifications and jobs ----------------------------------------------------------------------------
@router.post("/identifications", status_code=status.HTTP_202_ACCEPTED, response_model=JobPublic,
             responses=error_responses(400, 401, 403, 413))
def create_identification(body: IdentificationCreate, service: ServiceDep, _: OperatorDep) -> JobPublic:
    options = _options(body.method, body.options)
    try:
        job_id = service.engine.submit_identification(body.operating_point, body.method, options)
    except LimitError as exc:
        raise _limit_error(exc, ["body", "operating_point"]) from None
    except PlantTimeError as exc:
        raise _unprocessable(validation_error(["body", "options"], str(exc), "value_error.plant_time")) from None
    return _job_public(service, service.storage.get_job(job_id))


@router.get("/jobs", response_model=list[JobPublic])
def list_jobs(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[JobPublic]:
    return [_job_public(service, j) for j in service.storage.list_jobs(limit)]


@router.get("/jobs/{job_id}", response_model=JobPublic, responses=error_responses(404))
def get_job(job_id: ResourceId, service: ServiceDep) -> JobPublic:
    job = service.storage.get_job(job_id)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} does not exist")
    return _job_public(service, job)


@router.post("/jobs/{job_id}/cancel", response_model=JobPublic, responses=error_responses(401, 403, 404, 409))
def cancel_job(job_id: ResourceId, service: ServiceDep, _: OperatorDep) -> JobPublic:
    try:
        service.engine.cancel_job(job_id)
    except KeyError:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} does not exist") from None
    except TransitionError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return _job_public(service, service.storage.get_job(job_id))


@router.get("/results/{result_id}", responses=error_responses(404))
def get_result(result_id: ResourceId, service: ServiceDep) -> dict:
    row = service.storage.get_result(result_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"result {result_id} does not exist")
    return public_result(row)


# --- sweeps -------------------------------------------------------------------------------------------------
@router.post("/sweeps", status_code=status.HTTP_202_ACCEPTED, response_model=SweepPublic,
             responses=error_responses(400, 401, 403, 413))
def create_sweep(body: SweepCreate, service: ServiceDep, _: OperatorDep) -> SweepPublic:
    try:
        check_sweep_size(body.grid, body.confirm_large, service.settings.safety)
    except SweepTooLarge as exc:
        raise _unprocessable(validation_error(["body", "confirm_large"], str(exc), "value_error.confirm_large")) from None
    except ValueError as exc:
        raise _unprocessable(validation_error(["body", "grid"], str(exc))) from None
    options = _options(body.method, body.options)
    try:
        sweep_id = service.engine.submit_sweep(body.grid, body.method, options)
    except LimitError as exc:
        raise _limit_error(exc, ["body", "grid"]) from None
    except PlantTimeError as exc:
        raise _unprocessable(validation_error(["body", "options"], str(exc), "value_error.plant_time")) from None
    except ValueError as exc:
        raise _unprocessable(validation_error(["body", "grid"], str(exc))) from None
    return _sweep_public(service, service.storage.get_sweep(sweep_id))


@router.get("/sweeps", response_model=list[SweepPublic])
def list_sweeps(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[SweepPublic]:
    return [_sweep_public(service, s) for s in service.storage.list_sweeps(limit)]


@router.get("/sweeps/{sweep_id}", response_model=SweepPublic, responses=error_responses(404))
def get_sweep(sweep_id: ResourceId, service: ServiceDep) -> SweepPublic:
    sweep = service.storage.get_sweep(sweep_id)
    if sweep is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"sweep {sweep_id} does not exist")
    return _sweep_public(service, sweep, with_points=True)


@router.post("/sweeps/{sweep_id}/{action}", response_model=SweepPublic, responses=error_responses(401, 403, 404, 409))
def control_sweep(sweep_id: ResourceId, action: Literal["pause", "resume", "cancel"], service: ServiceDep,
                  _: OperatorDep) -> SweepPublic:
    handler = {"pause": service.engine.pause_sweep, "resume": service.engine.resume_sweep,
               "cancel": service.engine.cancel_sweep}[action]
    try:
        handler(sweep_id)
    except KeyError:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"sweep {sweep_id} does not exist in this service run") from None
    except TransitionError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return _sweep_public(service, service.storage.get_sweep(sweep_id))


# --- maps -----------------------------------------------------------------------------------------------------
@router.get("/maps")
def list_maps(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[dict]:
    return service.storage.list_maps(limit)


@router.get("/maps/{map_id}", responses=error_responses(404))
def get_map(map_id: ResourceId, service: ServiceDep) -> dict:
    m = public_map(service.storage, map_id)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    return m


_EXPORT_CONTENT = {media: {"schema": {"type": "object" if media == "application/json" else "string"}}
                   for media in {f.media_type for f in EXPORT_FORMATS.values()}}
ExportFormatName = Literal[tuple(EXPORT_FORMATS)]


@router.get("/maps/{map_id}/export",
            responses={200: {"description": "the map as a file", "content": _EXPORT_CONTENT}, **error_responses(404)})
def export(map_id: ResourceId, service: ServiceDep,
           format: ExportFormatName = Query("csv", description=" | ".join(
               f"{f.name}: {f.display_name}" for f in EXPORT_FORMATS.values()))) -> PlainTextResponse:
    m = public_map(service.storage, map_id)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    fmt = EXPORT_FORMATS[format]
    return PlainTextResponse(export_map(m, format), media_type=fmt.media_type,
                             headers={"Content-Disposition": f'attachment; filename="ripplecal_map{map_id}.{fmt.extension}"'})


@router.post("/maps/{map_id}/download", responses=error_responses(401, 403, 404, 409, 502))
def download_map(map_id: ResourceId, service: ServiceDep, _: OperatorDep) -> dict:
    """Build the map's LUT image and download it into the drive (0x2001), CRC read back."""
    m = public_map(service.storage, map_id)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    try:
        image = lut_image(m)
    except ValueError as exc:
        raise _unprocessable(validation_error(["path", "map_id"], f"map {map_id} cannot become a LUT: {exc}")) from None
    try:
        crc = service.bench.download_lut(image)
    except BenchError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except Exception as exc:   # SDO abort / timeout: the drive refused or did not answer
        raise HTTPException(status.HTTP_502_BAD_GATEWAY, f"drive refused the LUT: {exc}") from None
    return {"map_id": map_id, "bytes": len(image), "crc32": f"0x{crc:08X}", "cells": len(m["cells"]),
            "harmonic_order": m["harmonic_order"]}


# --- events -----------------------------------------------------------------------------------------------------
@router.get("/events")
async def events(request: Request, service: ServiceDep) -> StreamingResponse:
    token = service.broker.subscribe()
    _, queue = token

    async def stream():
        try:
            yield format_sse("bench.status", json.dumps(service.bench.status(), default=str))
            while True:
                if await request.is_disconnected():
                    break
                try:
                    event_type, data = await asyncio.wait_for(queue.get(), timeout=15.0)
                except asyncio.TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                yield format_sse(event_type, data)
        finally:
            service.broker.unsubscribe(token)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
