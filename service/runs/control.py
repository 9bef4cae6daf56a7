"""Pause, resume and cancel: of sweeps (between points; a cancel also inside a measurement) and of jobs.
The engine (service/runs/engine.py) holds one `Controls` and answers its `ControlHost` calls; every
state write still goes through the engine's tables. A cancel acts on the bench first (bench.stop_now),
before the database is asked; another bench's sweep is asked through the database
(service/runs/other_benches.py)."""

from __future__ import annotations

import threading
from typing import Any, Protocol

from service.bench.bench import Bench
from service.maps.build import build_map_from_sweep
from service.runs.other_benches import cancel_job_elsewhere, control_elsewhere
from service.runs.states import (
    JOB_TRANSITIONS,
    SWEEP_TRANSITIONS,
    JobState,
    SweepControl,
    SweepState,
    TransitionError,
    check_transition,
)
from service.runs.sweep_run import stored_sweep
from service.store.storage import Storage, StorageUnavailable, now_iso


class ControlHost(Protocol):
    """The engine, as its controls see it."""

    storage: Storage
    bench: Bench
    running_job: tuple[int, int | None] | None  # (job id, sweep id) the worker runs now

    @property
    def lock(self) -> threading.RLock: ...
    def is_own(self, bench: str | None) -> bool: ...
    def set_job(self, job_id: int, target: JobState, **fields: Any) -> None: ...
    def set_sweep(self, sweep_id: int, target: SweepState, **fields: Any) -> None: ...
    def publish_job(self, job_id: int) -> None: ...
    def publish_sweep(self, sweep_id: int) -> None: ...
    def queue_sweep(self, sweep_id: int) -> int: ...
    def wake_for(self, job_id: int) -> None: ...


class Controls:
    """The cancel and pause tokens of this process's jobs and sweeps, and the operator's actions on them."""

    def __init__(self, host: ControlHost):
        self.host = host
        self.sweeps: dict[int, SweepControl] = {}  # sweep id -> its pause / cancel tokens
        self.jobs: dict[int, threading.Event] = {}  # job id -> its cancel token (a sweep's job: the sweep's)

    def control_sweep(self, sweep_id: int, action: str) -> None:
        """`action`: pause | resume | cancel. Another bench's sweep: checked against the table here, then
        asked of its bench's service through the database (sweeps.control_request), which acts on it within
        about a second (act_on_control_requests); a queued one no service has taken is cancelled here.
        A cancel of the sweep this process runs acts on the bench first, before the database is asked."""
        if action == "cancel":
            self.cancel_running(sweep_id=sweep_id)
            known = self.host.storage.known_unavailable()
            if known is not None:  # the run (if any) is stopped: the rest waits for the database (503 at once)
                raise StorageUnavailable(known.cause, str(known), known.retry_after_s, known.public)
        try:
            sweep = self.host.storage.get_sweep(sweep_id)
        except StorageUnavailable:
            if action == "cancel":
                raise  # its run is stopped and its bench safe already (503: the rest when the database answers)
            return self.act(sweep_id, action)
        if sweep is None:
            raise KeyError(sweep_id)
        if self.host.is_own(sweep.get("bench")):
            return self.act(sweep_id, action)
        return control_elsewhere(self.host, sweep_id, sweep, action)

    def act(self, sweep_id: int, action: str) -> None:
        """One of SWEEP_ACTIONS on a sweep this process runs."""
        {"pause": self.pause_sweep, "resume": self.resume_sweep, "cancel": self.cancel_sweep}[action](sweep_id)

    def pause_sweep(self, sweep_id: int) -> None:
        """Pause takes effect between points: the run ends (bench made safe) and the sweep's job is parked,
        so other jobs run while it waits; resume queues it again."""
        with self.host.lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED)
            ctl = self.control(sweep_id)
            ctl.pause.set()
            if state == SweepState.QUEUED:
                self.host.set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
        self.host.publish_sweep(sweep_id)

    def resume_sweep(self, sweep_id: int) -> None:
        """Resume a paused sweep (its job is queued again: its next point is measured afresh, from a
        settled state), or one a previous service run left `interrupted` (queued again, it measures only
        the points not yet committed). Refused while an interlock is tripped."""
        with self.host.lock:
            state = self._sweep_state(sweep_id)
            if state not in (SweepState.PAUSED, SweepState.INTERRUPTED):
                raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused or interrupted")
            trip = self.host.bench.interlock_refusal()
            if trip is not None:
                raise TransitionError(
                    f"sweep {sweep_id} cannot resume: interlock tripped: {trip.reason}"
                    + ("; acknowledge it with POST /api/v1/bench/fault-reset" if trip.latched else "")
                )
            if state == SweepState.INTERRUPTED:
                self.host.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None, finished_at=None)
                self.host.queue_sweep(sweep_id)
                return
            ctl = self.control(sweep_id)
            ctl.pause.clear()
            self.host.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
            if ctl.parked_job is not None:
                job_id, ctl.parked_job = ctl.parked_job, None
                self.host.wake_for(job_id)
        self.host.publish_sweep(sweep_id)

    def cancel_sweep(self, sweep_id: int) -> None:
        with self.host.lock:
            try:
                state = self._sweep_state(sweep_id)
            except StorageUnavailable:
                if sweep_id in self.sweeps:
                    self.sweeps[sweep_id].cancel.set()  # the worker ends it when the database answers
                raise
            check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
            if state == SweepState.INTERRUPTED:
                self.host.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
            else:
                ctl = self.control(sweep_id)
                ctl.cancel.set()
                sweep = stored_sweep(self.host.storage, sweep_id)
                if ctl.parked_job is not None:
                    # paused with its job parked: nothing runs it, so it ends here with what it measured
                    job_id, ctl.parked_job = ctl.parked_job, None
                    map_id = (
                        build_map_from_sweep(self.host.storage, sweep_id, cancelled=True)
                        if sweep["started_at"]
                        and sweep.get("kind", "sweep") == "sweep"
                        and self.host.storage.sweep_results(sweep_id)
                        else sweep["map_id"]
                    )
                    self.host.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso(), map_id=map_id)
                    self.host.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
                elif state in (SweepState.QUEUED, SweepState.PAUSED) and not sweep["started_at"]:
                    self.host.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
        self.host.publish_sweep(sweep_id)

    def cancel_running(self, job_id: int | None = None, sweep_id: int | None = None) -> None:
        """A cancel of what the worker runs now: its token set and the bench made safe at once (the
        watchdog's thread), whatever the worker is doing; no database, no lock. Anything else: nothing."""
        running = self.host.running_job
        if running is None or not (
            (job_id is not None and running[0] == job_id) or (sweep_id is not None and running[1] == sweep_id)
        ):
            return
        if running[1] is not None:
            self.control(running[1]).cancel.set()
        if running[0] in self.jobs:
            self.jobs[running[0]].set()
        what = f"sweep {running[1]}" if running[1] is not None else f"job {running[0]}"
        self.host.bench.stop_now(f"{what} cancelled")

    def cancel_job(self, job_id: int) -> None:
        self.cancel_running(job_id=job_id)
        known = self.host.storage.known_unavailable()
        if known is not None:  # the run (if any) is stopped: the rest waits for the database (503 at once)
            raise StorageUnavailable(known.cause, str(known), known.retry_after_s, known.public)
        job = self.host.storage.get_job(job_id)
        if job is None:
            raise KeyError(job_id)
        check_transition(JOB_TRANSITIONS, JobState(job["state"]), JobState.CANCELLED)
        if job["sweep_id"] is not None:
            return self.cancel_sweep(job["sweep_id"])
        if not self.host.is_own(job.get("bench")):
            return cancel_job_elsewhere(self.host, job_id, job)
        self.jobs.setdefault(job_id, threading.Event()).set()
        if job["state"] == "queued":
            self.host.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())

    def _sweep_state(self, sweep_id: int) -> SweepState:
        sweep = self.host.storage.get_sweep(sweep_id)
        if sweep is None:
            raise KeyError(sweep_id)
        if not self.host.is_own(sweep.get("bench")):
            # only the bench's own service can stop its run between points
            raise TransitionError(
                f"sweep {sweep_id} is for bench {sweep['bench']}: ask the service of bench {sweep['bench']} "
                "(GET /api/v1/benches names its host and port)"
            )
        return SweepState(sweep["state"])

    def control(self, sweep_id: int) -> SweepControl:
        # a sweep of this bench queued by another bench's service gets its controls here, as it gets them
        # when the worker takes it
        return self.sweeps.setdefault(sweep_id, SweepControl())
