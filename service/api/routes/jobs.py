"""Identifications (one operating point, one method) and the jobs that run them."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Query, status

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.jobs import JobPublic, job_public
from service.api.refusals import refusals_at
from service.api.schemas import IdentificationCreate
from service.runs.plans import check_orders

router = APIRouter(prefix="/api/v1", tags=["identifications"])


@router.post(
    "/identifications",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobPublic,
    responses=error_responses(400, 401, 403, 409, 413),
    dependencies=[refusals_at(["body", "operating_point"], orders=["body", "orders"])],
)
def create_identification(body: IdentificationCreate, service: ServiceDep, _: OperatorDep) -> JobPublic:
    check_orders(body.orders, service.settings.identification.harmonic_order)
    job_id = service.engine.submit_identification(body.operating_point, body.method, body.options, bench=body.bench)
    return job_public(service.records, service.records.get_job(job_id), service)


@router.get("/jobs", response_model=list[JobPublic])
def list_jobs(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[JobPublic]:
    return [job_public(service.records, j, service) for j in service.records.list_jobs(limit)]


@router.get("/jobs/{job_id}", response_model=JobPublic, responses=error_responses(404))
def get_job(job_id: ResourceId, service: ServiceDep) -> JobPublic:
    job = service.records.get_job(job_id)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} does not exist")
    return job_public(service.records, job, service)


@router.post("/jobs/{job_id}/cancel", response_model=JobPublic, responses=error_responses(401, 403, 404, 409))
def cancel_job(job_id: ResourceId, service: ServiceDep, _: OperatorDep) -> JobPublic:
    service.cancel_job(job_id)
    return job_public(service.records, service.records.get_job(job_id), service)
