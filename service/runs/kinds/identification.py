"""Job kind `identification`: one operating point identified by one method (POST /jobs)."""

from __future__ import annotations

from typing import Any

from service.bench.trips import InterlockTripped
from service.identification.common import MethodOptions
from service.identification.session import Window
from service.model.limits import check_point
from service.model.operating_point import OperatingPoint
from service.runs.identify import check_plant_time, identify_at, parse_options
from service.runs.kinds.host import JobHost, JobKind
from service.runs.states import Cancelled
from service.runs.sweep_run import discard_recorder, error_text
from service.store.records import JobRecord
from service.store.result_rows import result_row
from service.store.storage import now_iso


def submit(host: JobHost, op: OperatingPoint, method: str, options: MethodOptions, bench: str | None = None) -> int:
    """`bench`: the bench it is for (default this one). Another bench's job is stored, and checked
    against that bench's settings by its own service when it takes it."""
    if host.is_own(bench):
        host.bench.check_reachable()  # refused now, not failed later
        check_point(op, host.settings, options.override_envelope_model)  # refuse before anything is queued
        check_plant_time([op.speed_rpm], method, options, host.settings)
    job_id = host.create_job(
        "identification",
        {"operating_point": op.model_dump(), "method": method, "options": options.model_dump()},
        bench=bench,
    )
    host.publish_job(job_id)
    return job_id


def check_here(host: JobHost, job: JobRecord) -> None:
    req = job["request"]
    op = OperatingPoint.model_validate(req["operating_point"])
    options = parse_options(req["method"], req["options"])
    check_point(op, host.settings, options.override_envelope_model)
    check_plant_time([op.speed_rpm], req["method"], options, host.settings)


def run(host: JobHost, job_id: int, job: JobRecord) -> None:
    req = job["request"]
    op = OperatingPoint.model_validate(req["operating_point"])
    options = parse_options(req["method"], req["options"])
    started = now_iso()

    def job_row(**outcome: Any) -> dict[str, Any]:
        """This job's `results` row with its outcome (a result, or an error)."""
        return result_row(op, req["method"], options, host.bench.identity, started, job_id=job_id, **outcome)

    recorder = host.new_recorder()
    cancel = host.cancel_token(job_id)
    try:
        result = identify_at(
            host.bench,
            host.settings,
            op,
            req["method"],
            options,
            cancel=cancel,
            progress=lambda w: publish_window(host, job_id, w),
            recorder=recorder,
        )
    except Exception as exc:
        if cancel.is_set() and not isinstance(exc, InterlockTripped):
            discard_recorder(recorder)
            raise Cancelled() from exc
        row = job_row(error=error_text(exc), harmonic_order=host.settings.identification.harmonic_order)
        rid = host.insert_result(row, recorder)
        host.storage.update_job(job_id, result_id=rid)
        raise
    row = job_row(result=result, harmonic_order=result.harmonic_order)
    stored: dict[str, int] = {}
    # the bench is safe (the run has ended): a database that cannot take the result now is waited for
    host.durably(lambda: stored.setdefault("id", host.insert_result(row, recorder)), f"job {job_id}: its result")
    if "id" in stored:
        host.durably(lambda: host.storage.update_job(job_id, result_id=stored["id"]), f"job {job_id}: its result")


def publish_window(host: JobHost, job_id: int, window: Window) -> None:
    """A run's accepted window as it comes (plant time on the DAQ clock, residual in full scale)."""
    host.broker.publish(
        "job.progress",
        {
            "job_id": job_id,
            "plant_time_s": window.end_time_s,
            "residual_fs": window.phasor.amplitude,
            "noise_std_fs": window.noise_std_fs,
        },
    )


KIND = JobKind("identification", submit=submit, check_here=check_here, run=run)
