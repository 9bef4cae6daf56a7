"""Surviving the night: what a previous process left unfinished, marked at start-up (`recover`), what this
process leaves at an orderly shutdown (`mark_unfinished`), and the sweeps resumed by themselves
(engine.auto_resume). Jobs and sweeps queued by another bench's service for this bench and not yet taken
wait untouched (service/runs/other_benches.py)."""

from __future__ import annotations

import logging
from typing import Any, Protocol

from service.runs.other_benches import waiting_sweeps, waits_for_bench
from service.runs.states import UNFINISHED_SWEEP_STATES, JobState, SweepState, TransitionError
from service.store.storage import Storage, now_iso

log = logging.getLogger(__name__)


class RecoveryHost(Protocol):
    """The engine, as recovery sees it."""

    storage: Storage
    bench_name: str
    instance: str

    @property
    def shutdown_reason(self) -> str: ...
    def set_job(self, job_id: int, target: JobState, **fields: Any) -> None: ...
    def set_sweep(self, sweep_id: int, target: SweepState, **fields: Any) -> None: ...
    def resume_sweep(self, sweep_id: int) -> None: ...


def auto_resume(host: RecoveryHost) -> None:
    """engine.auto_resume: every interrupted sweep of this bench resumed, unless something refuses it."""
    for sweep in host.storage.bench_unfinished_sweeps(host.bench_name):
        if sweep["state"] == SweepState.INTERRUPTED.value:
            log.warning("engine.auto_resume: resuming sweep %s (%s)", sweep["id"], sweep["pause_reason"])
            try:
                host.resume_sweep(sweep["id"])
            except TransitionError as exc:  # e.g. the drive faulted when we died: a person decides
                log.warning("engine.auto_resume: sweep %s stays interrupted: %s", sweep["id"], exc)
                host.set_sweep(
                    sweep["id"],
                    SweepState.INTERRUPTED,
                    pause_reason=f"{sweep['pause_reason']}; not resumed automatically: {exc}",
                )


def recover(host: RecoveryHost) -> None:
    """On start-up: what a previous process left unfinished. Jobs cannot still be running (failed,
    with the reason); sweeps become `interrupted` (not failed), resumable; a validation cut short
    keeps its points and says which LUT the drive was left holding."""
    held: dict[int, str] = {}
    jobs = host.storage.bench_unfinished_jobs(host.bench_name)
    kept = waiting_sweeps(jobs)
    for v in host.storage.bench_running_validations(host.bench_name):
        download = v["download"] or {}
        cells = v["cells"] or []
        lut = (
            f"the drive holds the LUT of map {download.get('map_id')} (CRC-32 {download.get('crc32')}) since this "
            "validation downloaded it"
        )
        error = f"the service stopped during this validation: {len(cells)} point(s) measured and kept; {lut}"
        host.storage.update_validation(v["id"], state="failed", error=error, finished_at=now_iso())
        held[v["job_id"]] = lut
    for job in jobs:
        if waits_for_bench(job, kept):
            continue  # queued for this bench while no service ran it: it runs now
        why = "the service stopped while this job was " + job["state"]
        if job["sweep_id"] is not None:
            why += f"; its sweep {job['sweep_id']} is interrupted: resume it"
        if job["id"] in held:
            why += f"; {held[job['id']]}"
        host.set_job(job["id"], JobState.FAILED, error=why, finished_at=now_iso())
    for sweep in host.storage.bench_unfinished_sweeps(host.bench_name):
        state = SweepState(sweep["state"])
        if state in UNFINISHED_SWEEP_STATES and sweep["id"] not in kept:
            reason = (
                f"the service stopped while this sweep was {state.value} (no orderly shutdown: crash or "
                f"kill); {sweep['done_points']} of {sweep['total_points']} points are stored, resume to "
                "measure the rest"
            )
            host.set_sweep(sweep["id"], SweepState.INTERRUPTED, pause_reason=reason)
    host.storage.adopt_unnamed_rows(host.bench_name)


def mark_unfinished(host: RecoveryHost) -> None:
    """At shutdown: jobs this process queued and did not run fail, unfinished sweeps are interrupted."""
    jobs = host.storage.bench_unfinished_jobs(host.bench_name)
    kept = waiting_sweeps(jobs)
    for job in jobs:  # what this process queued and did not run (a job queued elsewhere for the bench waits)
        if job["state"] == "queued" and job["claimed_by"] == host.instance:
            host.set_job(
                job["id"],
                JobState.FAILED,
                error=f"{host.shutdown_reason} before this job ran",
                finished_at=now_iso(),
            )
    for sweep in host.storage.bench_unfinished_sweeps(host.bench_name):
        state = SweepState(sweep["state"])
        if state in UNFINISHED_SWEEP_STATES and sweep["id"] not in kept:
            host.set_sweep(
                sweep["id"],
                SweepState.INTERRUPTED,
                pause_reason=f"{host.shutdown_reason} while this sweep was {state.value}; "
                f"{sweep['done_points']} of {sweep['total_points']} points are stored",
            )
