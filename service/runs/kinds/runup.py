"""Job kind `runup`: a speed ramp at constant torque, as an order analysis (service/runs/runup.py)."""

from __future__ import annotations

from typing import Any

from service import __version__
from service.bench.trips import InterlockTripped
from service.runs.kinds.host import JobHost, JobKind
from service.runs.runup import RunupRequest, check_runup, runup_in_run
from service.runs.states import Cancelled
from service.runs.sweep_run import discard_recorder, error_text
from service.store.records import JobRecord
from service.store.storage import now_iso


def submit(host: JobHost, req: RunupRequest) -> int:
    """Refused before anything is queued (limits, envelope along the range, ramp length); another bench's
    run-up is checked by its own service when it takes it."""
    if host.is_own(req.bench):
        host.bench.check_reachable()
        check_runup(req, host.settings)
    job_id = host.create_job("runup", req.model_dump(mode="json"), bench=req.bench)
    host.publish_job(job_id)
    return job_id


def check_here(host: JobHost, job: JobRecord) -> None:
    check_runup(RunupRequest.model_validate(job["request"]), host.settings)


def run(host: JobHost, job_id: int, job: JobRecord) -> None:
    """The run-up, stored however it ends (done with its analysis, failed with the reason); a cancel
    cancels the job and stores nothing measured."""
    req = RunupRequest.model_validate(job["request"])
    started = now_iso()
    recorder = host.new_recorder()
    cancel = host.cancel_token(job_id)

    def row(state: str, **fields: Any) -> dict[str, Any]:
        return {
            "job_id": job_id,
            "state": state,
            "request": req.model_dump(mode="json"),
            "bench_identity": host.bench.identity,
            "software_version": __version__,
            "started_at": started,
            "finished_at": now_iso(),
            **fields,
        }

    try:
        result = runup_in_run(host.bench, host.settings, req, cancel, recorder)
    except Exception as exc:
        discard_recorder(recorder)  # nothing analysed: no recording either
        if cancel.is_set() and not isinstance(exc, InterlockTripped):
            host.storage.insert_runup(row("cancelled", error="cancelled"))
            raise Cancelled() from exc
        host.storage.insert_runup(row("failed", error=error_text(exc)))
        raise
    # the bench is safe (the run has ended): a database that cannot take the result now is waited for
    host.durably(lambda: host.insert_runup(row("done", result=result), recorder), f"run-up {job_id}: its result")


KIND = JobKind("runup", submit=submit, check_here=check_here, run=run)
