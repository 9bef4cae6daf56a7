"""Job kind `validation`: a map validated in the drive's LUT mode (service/runs/validation.py)."""

from __future__ import annotations

from typing import Any

from service.errors import NotFound
from service.runs.kinds.host import JobHost, JobKind
from service.runs.states import Cancelled
from service.runs.validation import (
    ValidationOptions,
    ValidationStopped,
    check_points,
    check_validatable,
    run_validation,
    store_validation,
)
from service.store.records import JobRecord


def submit(host: JobHost, map_id: int, force: bool, options: ValidationOptions, bench: str | None = None) -> int:
    """Refused before anything is queued: KeyError (no such map), ValidationRefused (no valid cell, partial
    without force), LimitError (a point outside the bench's limits; another bench's service checks its own)."""
    own = host.is_own(bench)
    if own:
        host.bench.check_reachable()
    row = host.storage.get_map(map_id)
    if row is None:
        raise KeyError(map_id)
    check_validatable(host.storage, map_id, force, fill=options.fill)
    if own:
        check_points(row["axes"], host.settings, options.override_envelope_model)
    job_id = host.create_job(
        "validation", {"map_id": map_id, "force": force, "options": options.model_dump()}, bench=bench
    )
    host.publish_job(job_id)
    return job_id


def check_here(host: JobHost, job: JobRecord) -> None:
    req = job["request"]
    override = bool(req["options"].get("override_envelope_model", False))
    row = host.storage.get_map(req["map_id"])
    if row is None:
        raise NotFound(f"map {req['map_id']} does not exist")
    check_points(row["axes"], host.settings, override)


def run(host: JobHost, job_id: int, job: JobRecord) -> None:
    """Download, then every point; the validation is stored however it ends (the map keeps its
    latest). An interlock trip or a point's stop fails the job with the reason; a cancel cancels it.
    The bench is made safe after every point (bench.operating_point)."""
    req = job["request"]
    options = ValidationOptions.model_validate(req["options"])

    def on_cell(cell: dict[str, Any], total: int) -> None:
        host.broker.publish("job.progress", {"job_id": job_id, "kind": "validation", "total": total, "cell": cell})

    run = run_validation(
        host.storage,
        host.bench,
        host.settings,
        req["map_id"],
        req["force"],
        options,
        host.cancel_token(job_id),
        on_cell=on_cell,
        on_progress=lambda r: store_validation(host.storage, job_id, r, host.bench.identity, finished=False),
    )
    store_validation(host.storage, job_id, run, host.bench.identity)
    if run.state == "cancelled":
        raise Cancelled()
    if run.state == "failed":
        raise ValidationStopped(run.error)


KIND = JobKind("validation", submit=submit, check_here=check_here, run=run)
