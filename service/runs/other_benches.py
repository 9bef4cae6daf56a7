"""The work for other benches, and other benches' work for this one, through the shared database:
a job or sweep queued here for another bench waits in the database for that bench's service; pause,
resume and cancel of another bench's sweep are asked through the database (sweeps.control_request) and
acted on by that bench's service (`act_on_control_requests`, every second); a queued one no service has
taken yet is cancelled here with a conditional write. Recovery leaves such waiting work untouched."""

from __future__ import annotations

import logging
from typing import Any, Mapping, Protocol, Sequence

from service.runs.states import (
    JOB_TRANSITIONS,
    SWEEP_TRANSITIONS,
    JobState,
    SweepState,
    TransitionError,
    check_transition,
)
from service.store.storage import Storage

log = logging.getLogger(__name__)

SWEEP_ACTIONS = ("pause", "resume", "cancel")  # what an operator may ask of a sweep (control_sweep)


class DatabaseHost(Protocol):
    """What asking another bench's service through the database needs."""

    storage: Storage

    def publish_sweep(self, sweep_id: int) -> None: ...
    def publish_job(self, job_id: int) -> None: ...


class ControlHost(DatabaseHost, Protocol):
    """The engine, as other benches' requests for this bench's sweeps see it."""

    bench_name: str

    def act(self, sweep_id: int, action: str) -> None: ...


def waiting_sweeps(jobs: Sequence[Mapping[str, Any]]) -> set[int]:
    """Sweeps of this bench queued by another bench's service and not yet taken: they wait, untouched."""
    return {
        j["sweep_id"]
        for j in jobs
        if j["sweep_id"] is not None and j["state"] == "queued" and j["claimed_by"] is None and j["bench"]
    }


def waits_for_bench(job: Mapping[str, Any], kept: set[int]) -> bool:
    """A job of this bench that no service has taken yet (queued elsewhere for it): not recovered."""
    if job["state"] != "queued" or job["claimed_by"] is not None or job["bench"] is None:
        return False
    return job["sweep_id"] is None or job["sweep_id"] in kept


def control_elsewhere(host: DatabaseHost, sweep_id: int, sweep: Mapping[str, Any], action: str) -> None:
    """Another bench's sweep: checked against the table here, then asked of its bench's service through
    the database; a queued one no service has taken is cancelled here."""
    state = SweepState(sweep["state"])
    if action == "cancel" and state == SweepState.QUEUED:
        check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
        check_transition(JOB_TRANSITIONS, JobState.QUEUED, JobState.CANCELLED)
        if host.storage.cancel_waiting_sweep(sweep_id):
            return host.publish_sweep(sweep_id)
    if action == "resume":
        if state not in (SweepState.PAUSED, SweepState.INTERRUPTED):
            raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused or interrupted")
    else:
        check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED if action == "pause" else SweepState.CANCELLED)
    host.storage.request_sweep_control(sweep_id, action)
    host.publish_sweep(sweep_id)


def cancel_job_elsewhere(host: DatabaseHost, job_id: int, job: Mapping[str, Any]) -> None:
    """Another bench's job (not a sweep's): cancelled here only while no service has taken it."""
    if job["state"] != "queued":  # its run is in the other service's hands
        raise TransitionError(f"job {job_id} runs on bench {job['bench']}: ask the service of that bench")
    # queued: no service has taken it; a conditional write, so a claim at this moment wins cleanly
    if not host.storage.cancel_queued_job(job_id):
        raise TransitionError(f"job {job_id} was taken by bench {job['bench']} just now: ask its service")
    host.publish_job(job_id)


def act_on_control_requests(host: ControlHost) -> None:
    """Pause, resume or cancel asked at another bench's service for this bench's sweeps (the lab thread
    calls this every second). A refusal is noted on the sweep (control_note) for whoever asked."""
    for sweep_id, action in host.storage.sweep_control_requests(host.bench_name):
        if action not in SWEEP_ACTIONS or not host.storage.take_sweep_control(sweep_id, action):
            continue
        try:
            host.act(sweep_id, action)
        except (TransitionError, KeyError) as exc:
            note = f"{action} asked at another bench's service: refused by bench {host.bench_name}: {exc}"
            log.warning("sweep %s: %s", sweep_id, note)
            host.storage.update_sweep(sweep_id, control_note=note)
            host.publish_sweep(sweep_id)
