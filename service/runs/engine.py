"""The run engine: one worker thread owns the bench and runs queued jobs one at a time.

The engine owns the queue and the worker, and every state write: `set_job` / `set_sweep` check the
state tables (service/runs/states.py); any other transition is a bug and raises. What a job does is its
kind's (service/runs/kinds: submit checks, plan, run body, looked up by the job's kind); pause / resume /
cancel are service/runs/control.py, recovery service/runs/recovery.py, the work for other benches
service/runs/other_benches.py, the waits for a database that cannot be used service/runs/database_away.py:
each calls back only through the engine's host methods. The bench is left safe (torque off, injection
off) however a job ends.
"""

from __future__ import annotations

import collections
import logging
import threading
import traceback
from typing import Any, Callable, ContextManager, Mapping

from drivers.errors import DriverError
from service.bench.bench import Bench
from service.errors import NotFound, ServiceError
from service.identification.common import MethodOptions
from service.model.operating_point import OperatingPoint
from service.runs import recovery
from service.runs.control import Controls
from service.runs.database_away import StorageWaits, durably
from service.runs.events import EventBroker
from service.runs.kinds import KINDS, kind_of
from service.runs.lab import is_own_bench, job_event, new_instance_id, sweep_event
from service.runs.other_benches import act_on_control_requests
from service.runs.plans import Grid, PlannedGrid, RegimePlacement
from service.runs.states import (
    JOB_TRANSITIONS,
    SWEEP_TRANSITIONS,
    Cancelled,
    JobState,
    Paused,
    State,
    SweepControl,
    SweepState,
    TransitionError,
    check_transition,
)
from service.runs.sweep_run import SweepRunner, error_text, job_sweep_id, stored_sweep
from service.settings import Settings
from service.store.recordings import RecordingStore, RunRecorder
from service.store.records import JobRecord, SweepRecord
from service.store.storage import Storage, StorageUnavailable, now_iso

log = logging.getLogger(__name__)


# what a bench and its measurements answer in the normal course (a refusal, a trip, a point that cannot
# be measured, a device that does not answer): every ServiceError (service/errors.py) and a driver's error
# (drivers/ sits below the service's root): logged in one line; anything else is a bug, with its traceback
EXPECTED_FAILURES = (ServiceError, DriverError)


CLAIM_POLL_S = 0.5  # the worker looks for its bench's jobs this often (and at once when this process queues one)


class Engine:
    def __init__(
        self,
        storage: Storage,
        bench: Bench,
        settings: Settings,
        broker: EventBroker,
        recordings: RecordingStore | None = None,
        instance: str | None = None,
        lab: bool = False,
    ):
        """`instance`: this process's id in the lab (service/runs/lab.py). `lab`: the worker takes every job
        the database holds for this bench (a serve); else only the jobs this engine queued itself (a CLI
        run beside a serve of the same bench must not take the serve's jobs)."""
        self.storage, self.bench, self.settings, self.broker = storage, bench, settings, broker
        self.recordings = recordings  # raw recording of every identification (None: none kept)
        self.bench_name = settings.bench_name
        self.instance = instance or new_instance_id()
        self.lab = lab
        self._wake = threading.Event()  # a job of this bench was queued here: claim it now, not at the next poll
        self._mine: collections.deque[int] = collections.deque()  # without `lab`: the jobs this engine queued
        self.running: str | None = None  # what the worker runs now (the bench's heartbeat shows it)
        self.running_job: tuple[int, int | None] | None = None  # (job id, sweep id) the worker runs now
        self.controls = Controls(self)  # pause / cancel tokens and the operator's actions (service/runs/control.py)
        self._storage_waits = StorageWaits()  # sweeps whose run waits for the database (in memory only)
        self._lock = threading.RLock()  # state read-check-write of jobs and sweeps
        self._thread: threading.Thread | None = None
        self._shutdown = threading.Event()
        self._shutdown_reason = "service shut down"
        self.sweeps = SweepRunner(self)  # a sweep's run body (service/runs/sweep_run.py), a refinement's rounds use it

    # --- what a sweep's run body needs from its engine (service/runs/sweep_run.py RunHost) -------------
    @property
    def lock(self) -> threading.RLock:
        return self._lock

    @property
    def shutdown_reason(self) -> str:
        return self._shutdown_reason

    def shutting_down(self) -> bool:
        return self._shutdown.is_set()

    # --- lifecycle -----------------------------------------------------------------------------------
    def start(self, recover: bool = True) -> None:
        """`recover`: mark what a previous process left unfinished (only the process that owns the
        database's runs does this: a CLI run beside a server must not touch the server's work)."""
        if recover:
            self.recover()
        self._thread = threading.Thread(target=self._work, name="ripplecal-engine", daemon=True)
        self._thread.start()
        if recover and self.settings.engine.auto_resume:
            recovery.auto_resume(self)

    def recover(self) -> None:
        """On start-up: what a previous process left unfinished (service/runs/recovery.py)."""
        recovery.recover(self)

    def stop(self, reason: str | None = None, timeout_s: float = 30.0) -> None:
        """Orderly shutdown: the run in flight stops (bench left safe), unfinished sweeps become
        `interrupted` with `reason` (e.g. "service shut down (SIGTERM)") in their pause_reason."""
        if reason:
            self._shutdown_reason = reason
        if self.running_job is not None:
            # the bench first, at once: the worker may be stuck (on the database) inside its run
            self.bench.stop_now(self._shutdown_reason)
        self._shutdown.set()
        for ctl in list(self.controls.sweeps.values()):
            ctl.cancel.set()
        for ev in list(self.controls.jobs.values()):
            ev.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning(
                    "the engine's worker did not end within %.0f s of the shutdown (stuck on the database?): what "
                    "it ran is marked interrupted here if the database answers, else at the next start",
                    timeout_s,
                )
        known = self.storage.known_unavailable()
        try:
            if known is not None:  # not waited for again: the worker's last try has just said so
                raise known
            recovery.mark_unfinished(self)
        except StorageUnavailable as exc:
            log.warning("shutdown: unfinished jobs and sweeps not marked (%s): the next start does it", exc)

    # --- state writes (every one through the tables) ----------------------------------------------------------
    def set_job(self, job_id: int, target: JobState, **fields: Any) -> None:
        """Check the transition, write it, tell the subscribers (SSE)."""
        self._set_state(
            f"job {job_id}",
            JOB_TRANSITIONS,
            JobState,
            lambda: self.storage.get_job(job_id),
            lambda **f: self.storage.update_job(job_id, **f),
            target,
            fields,
        )
        self.publish_job(job_id)

    def set_sweep(self, sweep_id: int, target: SweepState, **fields: Any) -> None:
        """Check the transition, write it, tell the subscribers (SSE). A same-state write only updates
        fields (e.g. a new pause_reason)."""
        self._set_state(
            f"sweep {sweep_id}",
            SWEEP_TRANSITIONS,
            SweepState,
            lambda: self.storage.get_sweep(sweep_id),
            lambda **f: self.storage.update_sweep(sweep_id, **f),
            target,
            fields,
        )
        self.publish_sweep(sweep_id)

    def _set_state(
        self,
        what: str,
        table: Mapping[State, frozenset[State]],
        states: Callable[[str], State],
        read: Callable[[], JobRecord | SweepRecord | None],
        update: Callable[..., None],
        target: State,
        fields: dict[str, Any],
    ) -> None:
        """One state write through its table. Waits for a database that is unavailable (lock, read-only or
        full filesystem) until it takes the write or the service stops."""

        def write() -> None:
            with self._lock:
                row = read()
                if row is None:
                    raise NotFound(f"{what} does not exist")
                current = states(row["state"])
                if current != target:
                    check_transition(table, current, target)
                update(state=target.value, **fields)

        if not self.durably(write, f"{what}: state {target.value}"):
            raise StorageUnavailable("shutdown", f"{what}: state {target.value} not written (service stopping)")

    # --- submitting --------------------------------------------------------------------------------------
    def submit(self, kind: str, *args: Any, **kwargs: Any) -> int:
        """Check, store and queue a job of `kind` (service/runs/kinds: its module's `submit`); `bench` (a
        keyword of every kind): the bench it is for (default this one), see service/runs/other_benches.py."""
        return KINDS[kind].submit(self, *args, **kwargs)

    # the kinds by name, as the service, the CLI and the schedules call them
    def submit_identification(
        self, op: OperatingPoint, method: str, options: MethodOptions, bench: str | None = None
    ) -> int:
        return self.submit("identification", op, method, options, bench=bench)

    def submit_sweep(
        self,
        grid: Grid,
        method: str,
        options: MethodOptions,
        schedule_id: int | None = None,
        regime: RegimePlacement | None = None,
        bench: str | None = None,
        planned: PlannedGrid | None = None,
    ) -> int:
        return self.submit("sweep", grid, method, options, schedule_id, regime, bench=bench, planned=planned)

    def is_own(self, bench: str | None) -> bool:
        return is_own_bench(bench, self.bench_name)

    def create_job(self, kind: str, request: dict[str, Any], bench: str | None, sweep_id: int | None = None) -> int:
        """A job for this bench is this instance's from the start (claimed_by: no other service takes it; a
        crash leaves it to recovery); one for another bench waits for whichever service serves that bench."""
        own = self.is_own(bench)
        job_id = self.storage.create_job(
            kind,
            request,
            sweep_id=sweep_id,
            bench=self.bench_name if own else bench,
            claimed_by=self.instance if own else None,
        )
        if own:
            if sweep_id is None:
                self.controls.jobs[job_id] = threading.Event()
            self.wake_for(job_id)
        return job_id

    def wake_for(self, job_id: int) -> None:
        """A job of this bench was queued (or queued again) here: the worker claims it now."""
        self._mine.append(job_id)
        self._wake.set()

    def queue_sweep(self, sweep_id: int) -> int:
        sweep = stored_sweep(self.storage, sweep_id)
        kind = sweep.get("kind") or "sweep"  # a refinement runs as a sweep of its kind
        if self.is_own(sweep.get("bench")):
            self.controls.sweeps[sweep_id] = SweepControl()
        job_id = self.create_job(kind, {"sweep_id": sweep_id}, bench=sweep.get("bench"), sweep_id=sweep_id)
        if sweep_id in self.controls.sweeps:
            self.controls.jobs[job_id] = self.controls.sweeps[sweep_id].cancel
        self.publish_sweep(sweep_id)
        return job_id

    # --- pause, resume, cancel (service/runs/control.py) --------------------------------------------------
    def control_sweep(self, sweep_id: int, action: str) -> None:
        """`action`: pause | resume | cancel (another bench's sweep: asked through the database)."""
        self.controls.control_sweep(sweep_id, action)

    def resume_sweep(self, sweep_id: int) -> None:
        self.controls.resume_sweep(sweep_id)

    def cancel_job(self, job_id: int) -> None:
        self.controls.cancel_job(job_id)

    def act(self, sweep_id: int, action: str) -> None:
        self.controls.act(sweep_id, action)

    def control(self, sweep_id: int) -> SweepControl:
        return self.controls.control(sweep_id)

    def act_on_control_requests(self) -> None:
        """Control asked at another bench's service for this bench's sweeps (service/runs/other_benches.py)."""
        act_on_control_requests(self)

    # --- the worker ------------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job_id = self._next_job()
            if job_id is None:
                return
            try:
                self._work_on(job_id)
            except TransitionError as exc:
                # a state the table refuses (e.g. a sweep cancelled as the worker took it): the job is
                # over either way; the worker must live on for the next one
                log.warning("job %s ended with a refused transition: %s", job_id, exc)
            except Exception:
                log.error("job %s: the worker caught an error it did not expect: %s", job_id, traceback.format_exc())
            finally:
                self.running = None
                self.running_job = None

    def _next_job(self) -> int | None:
        """The next job of this bench, taken from the database (queued -> running in one conditional write,
        Storage.claim_job): polled every CLAIM_POLL_S, at once when this process queued one. None: stopping."""
        check_transition(JOB_TRANSITIONS, JobState.QUEUED, JobState.RUNNING)  # the claim's write, by the table
        while not self._shutdown.is_set():
            try:
                job_id = self._claim()
            except StorageUnavailable as exc:
                log.info("claiming the next job: the database is unavailable (%s)", exc.cause)
                job_id = None
            if job_id is not None:
                return job_id
            self._wake.wait(CLAIM_POLL_S)
            self._wake.clear()
        return None

    def _claim(self) -> int | None:
        if self.lab:
            self._mine.clear()  # the database holds them all
            return self.storage.claim_job(self.bench_name, self.instance)
        while self._mine:
            job_id = self.storage.claim_job(self.bench_name, self.instance, job_id=self._mine[0])
            self._mine.popleft()
            if job_id is not None:
                return job_id
        return None

    def _work_on(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        if job is None or job["state"] != "running" or job["claimed_by"] != self.instance:
            return
        if job["sweep_id"] is not None:  # taken from the database: its controls live in this process now
            self.controls.jobs[job_id] = self.controls.control(job["sweep_id"]).cancel
        # what it is, as the lab lists it: "sweep 4", "refinement 5" (a sweep's id), "runup job 7"
        what = job["kind"]
        self.running = f"{what} {job['sweep_id']}" if job["sweep_id"] is not None else f"{what} job {job_id}"
        self.running_job = (job_id, job["sweep_id"])
        cancel = self.controls.jobs.setdefault(job_id, threading.Event())
        if self._shutdown.is_set():
            self.set_job(
                job_id, JobState.FAILED, error=f"{self._shutdown_reason} before this job ran", finished_at=now_iso()
            )
            return
        if cancel.is_set():
            self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
            return
        self.publish_job(job_id)  # the claim wrote running and started_at (Storage.claim_job)
        try:
            kind = kind_of(job["kind"])
            # a job queued by another bench's service was checked only from its request: this bench's limits
            # and plant time now (it fails, and its sweep, with the reason); one queued here passed the same
            # checks at submit: checked again, as cheap as it is deterministic
            kind.check_here(self, job)
            kind.run(self, job_id, job)
            final = JobState.CANCELLED if cancel.is_set() else JobState.DONE
            self.set_job(
                job_id, final, finished_at=now_iso(), error=self._shutdown_reason if self._shutdown.is_set() else None
            )
        except Paused:  # only a sweep's job pauses
            self._park(job_id, job_sweep_id(job))
        except Cancelled:
            self.set_job(
                job_id,
                JobState.CANCELLED,
                finished_at=now_iso(),
                error=self._shutdown_reason if self._shutdown.is_set() else None,
            )
        except Exception as exc:
            error = error_text(exc)
            if isinstance(exc, EXPECTED_FAILURES):
                log.warning("job %s failed: %s", job_id, error)  # the bench said no: one line, no traceback
            else:
                log.error("job %s failed: %s", job_id, traceback.format_exc())
            self.set_job(job_id, JobState.FAILED, error=error, finished_at=now_iso())
            sweep = self.storage.get_sweep(job["sweep_id"]) if job["sweep_id"] is not None else None
            if sweep is not None and SweepState(sweep["state"]) not in (
                SweepState.CANCELLED,
                SweepState.DONE,
                SweepState.FAILED,
            ):
                self.set_sweep(sweep["id"], SweepState.FAILED, error=error, finished_at=now_iso())
        self.publish_job(job_id)

    def _park(self, job_id: int, sweep_id: int) -> None:
        """The sweep paused between points: its job waits, queued but out of the worker's queue, until
        resume puts it back (or cancel ends it); the worker goes on with the next job."""
        with self._lock:
            ctl = self.controls.sweeps[sweep_id]
            if SweepState(stored_sweep(self.storage, sweep_id)["state"]) != SweepState.PAUSED:
                self.set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
            self.set_job(job_id, JobState.QUEUED)
            if ctl.pause.is_set():
                ctl.parked_job = job_id
            else:  # resumed while the run was ending: straight back into the queue
                self.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
                self.wake_for(job_id)
        log.info("sweep %s paused: its job %s waits; the bench is free for other jobs", sweep_id, job_id)

    def new_recorder(self) -> RunRecorder | None:
        return self.recordings.recorder() if self.recordings is not None else None

    def insert_result(self, row: dict[str, Any], recorder: RunRecorder | None) -> int:
        """Store the result, then write its raw recording: a recording that fails is noted in the
        stored row and never loses the result."""
        rid = self.storage.insert_result(row)
        if self.recordings is not None:
            self.recordings.keep(recorder, rid, row)
        return rid

    def insert_runup(self, row: dict[str, Any], recorder: RunRecorder | None) -> int:
        """Store the run-up, then write its raw recording (as insert_result)."""
        runup_id = self.storage.insert_runup(row)
        if self.recordings is not None:
            self.recordings.keep_runup(recorder, runup_id, row)
        return runup_id

    def cancel_token(self, job_id: int) -> threading.Event:
        """The cancel of the job the worker runs (set by cancel_job / cancel_sweep / stop)."""
        return self.controls.jobs[job_id]

    # --- events ----------------------------------------------------------------------------------------------
    def publish_job(self, job_id: int) -> None:
        try:
            job = self.storage.get_job(job_id)
        except StorageUnavailable:
            return  # the dashboard hears of it when the database answers again
        if job is not None:
            self.broker.publish("job.state", job_event(job))

    def publish_sweep(self, sweep_id: int) -> None:
        try:
            s = self.storage.get_sweep(sweep_id)
        except StorageUnavailable:
            return
        if s is not None:
            self.broker.publish("sweep.progress", sweep_event(self.as_seen(s)))

    # --- the database away (service/runs/database_away.py) ----------------------------------------------------
    def durably(self, write: Callable[[], object], what: str, cancel: threading.Event | None = None) -> bool:
        # only the worker waits: an API request is answered at once (503), never held
        on_worker = threading.current_thread() is self._thread
        return durably(write, what, self._shutdown, cancel, on_worker)

    def waiting_for_storage(self, sweep_id: int, reason: str) -> ContextManager[None]:
        return self._storage_waits.waiting(sweep_id, reason)

    def as_seen(self, sweep: SweepRecord) -> SweepRecord:
        return self._storage_waits.as_seen(sweep)
