"""A job (an identification, a validation, a refinement, a sweep's run) with what it produced."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from pydantic import BaseModel, Field

from service.api.public.benches import queued_waiting_for
from service.api.public.refinements import RefinementPublic, refinement_public
from service.api.public.results import ResultPublic, result_public
from service.api.public.runups import RunupPublic, runup_public
from service.api.public.validations import ValidationPublic, validation_public

if TYPE_CHECKING:
    from service.calibration_service import CalibrationService, Records


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
    result: ResultPublic | RefinementPublic | RunupPublic | None = Field(
        None,
        description="kind identification: the result; kind "
        "refinement: the refined map, its rounds, the cells added "
        "and the final validation; kind runup: its order analysis",
    )
    validation: ValidationPublic | None = Field(
        None, description="kind validation: the map's LUT measured in the drive's LUT mode, every cell"
    )


def job_public(records: Records, job: Mapping[str, Any], service: CalibrationService | None = None) -> JobPublic:
    """`service`: the running service, for what a queued job waits for and a refinement's sweep as its run
    sees it (None: the database alone, as the CLI reads it)."""
    row = records.get_result(job["result_id"]) if job.get("result_id") else None
    validation = records.validation_of_job(job["id"]) if job["kind"] == "validation" else None
    result: ResultPublic | RefinementPublic | RunupPublic | None = result_public(row) if row else None
    if job["kind"] == "runup":
        runup = records.runup_of_job(job["id"])
        result = runup_public(runup) if runup is not None else None
    if job["kind"] == "refinement" and job["sweep_id"] is not None:
        sweep = service.seen_sweep(job["sweep_id"]) if service is not None else records.get_sweep(job["sweep_id"])
        if sweep is None:  # the job's row names it (a foreign key): a store that lost it is broken
            raise LookupError(f"refinement job {job['id']}: its sweep {job['sweep_id']} is not stored")
        result = refinement_public(records, sweep)
    return JobPublic(
        id=job["id"],
        kind=job["kind"],
        state=job["state"],
        bench=job.get("bench"),
        waiting_for=queued_waiting_for(service, job),
        request=job["request"],
        sweep_id=job["sweep_id"],
        error=job["error"],
        created_at=job["created_at"],
        started_at=job["started_at"],
        finished_at=job["finished_at"],
        result=result,
        validation=validation_public(validation) if validation else None,
    )
