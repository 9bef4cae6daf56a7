"""Run-ups: a speed ramp at constant torque, judged by order analysis (a job of kind `runup`)."""

from __future__ import annotations

from fastapi import APIRouter, Query, status

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.jobs import JobPublic, job_public
from service.api.refusals import refusals_at
from service.errors import NotFound
from service.runs.runup import RunupRequest

router = APIRouter(prefix="/api/v1", tags=["runups"])


@router.post(
    "/runups",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobPublic,
    responses=error_responses(400, 401, 403, 409, 413),
    dependencies=[refusals_at(["body"])],
)
def create_runup(body: RunupRequest, service: ServiceDep, _: OperatorDep) -> JobPublic:
    job_id = service.engine.submit("runup", body)
    return job_public(service.records, service.records.get_job(job_id), service)


@router.get("/runups", response_model=list[JobPublic])
def list_runups(service: ServiceDep, limit: int = Query(20, ge=1, le=200)) -> list[JobPublic]:
    """The newest run-up jobs first, each with its order analysis."""
    return [job_public(service.records, j, service) for j in service.records.list_jobs(limit, kind="runup")]


@router.get("/runups/{job_id}", response_model=JobPublic, responses=error_responses(404))
def get_runup(job_id: ResourceId, service: ServiceDep) -> JobPublic:
    """The same job as GET /jobs/{id}, for a job of kind runup."""
    job = service.records.get_job(job_id)
    if job is None or job["kind"] != "runup":
        raise NotFound(f"run-up {job_id} does not exist")
    return job_public(service.records, job, service)
