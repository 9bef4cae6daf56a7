"""The run engine: one worker thread owns the bench and runs queued jobs one at a time.

State machines are tables (an Enum plus the transitions allowed); every state write goes through
`_set_job` / `_set_sweep`, which check the table; any other transition is a bug and raises. A sweep
runs its plan point by point; each point's result is committed in its own transaction before the
next point starts, and a failing point is stored as failed and the sweep goes on. Pause takes effect
between points: the run ends (bench safe) and the sweep's job is parked (queued, out of the worker's
queue), so other jobs run while the sweep waits; resume queues it again. Cancel acts between points or
inside a measurement; the bench is left safe (torque off, injection off) in every case.

Surviving the night: an interlock trip discards the point in flight (stored as a failed,
discarded attempt, never ok), pauses the sweep with the reason and measures that point again on
resume. A sweep the service stopped under (crash, kill -9, shutdown) is `interrupted` when the
service starts again; resume (or `engine.auto_resume`) measures only the points not yet committed,
and each point keeps one current result (earlier attempts are history: results.superseded_by).
"""

from __future__ import annotations

import logging
import queue
import threading
import traceback
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable

from drivers.errors import DriverError
from service import __version__
from service.bench.bench import BenchError
from service.bench.interlocks import InterlockTripped
from service.bench.setpoint_accounting import AccountingError
from service.identification.common import LUT_MARGIN_DB
from service.identification.session import MeasurementError
from service.maps.build import build_map, build_map_from_sweep
from service.maps.neighbours import prior_from_neighbours
from service.maps.view import map_view
from service.model.limits import LimitError, check_limits
from service.model.operating_point import OperatingPoint
from service.runs.events import EventBroker
from service.runs.identify import check_plant_time, identify_at, identify_in_run, parse_options, run_settings
from service.runs.plans import Grid, SweepPlan, plan_grid
from service.runs.refinement import MAX_ROUNDS, RefineRequest, axes_with, check_request, plan_round
from service.runs.validation import (
    ValidationOptions,
    ValidationStopped,
    check_points,
    check_validatable,
    run_validation,
    store_validation,
)
from service.settings import Settings
from service.store.recordings import RecordingStore, RunRecorder
from service.store.result_rows import result_row
from service.store.storage import Storage, StorageUnavailable, now_iso

log = logging.getLogger(__name__)


class JobState(str, Enum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


class SweepState(str, Enum):
    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    INTERRUPTED = "interrupted"  # the service stopped under it; resume measures what is missing
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


J, W = JobState, SweepState
JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    J.QUEUED: frozenset({J.RUNNING, J.CANCELLED, J.FAILED}),  # failed: the service stopped before it ran
    J.RUNNING: frozenset({J.DONE, J.FAILED, J.CANCELLED, J.QUEUED}),  # queued: its sweep paused (parked)
    J.DONE: frozenset(),
    J.FAILED: frozenset(),
    J.CANCELLED: frozenset(),
}
SWEEP_TRANSITIONS: dict[SweepState, frozenset[SweepState]] = {
    W.QUEUED: frozenset({W.RUNNING, W.CANCELLED, W.PAUSED, W.INTERRUPTED}),
    W.RUNNING: frozenset({W.PAUSED, W.DONE, W.FAILED, W.CANCELLED, W.INTERRUPTED}),
    W.PAUSED: frozenset({W.RUNNING, W.CANCELLED, W.QUEUED, W.INTERRUPTED}),
    W.INTERRUPTED: frozenset({W.QUEUED, W.CANCELLED}),
    W.DONE: frozenset(),
    W.FAILED: frozenset(),
    W.CANCELLED: frozenset(),
}
UNFINISHED_SWEEP_STATES = frozenset({W.QUEUED, W.RUNNING, W.PAUSED})
STORAGE_RETRY_S = (0.5, 10.0)  # first and longest pause between tries of a database that is unavailable
del J, W


# what a bench and its measurements answer in the normal course (a refusal, a trip, a point that cannot
# be measured, a device that does not answer): logged in one line; anything else is a bug, with its traceback
EXPECTED_FAILURES = (
    InterlockTripped,
    MeasurementError,
    LimitError,
    DriverError,
    BenchError,
    AccountingError,
    ValidationStopped,
)


class TransitionError(RuntimeError):
    """A request that the current state does not allow (e.g. resume a finished sweep)."""


class Cancelled(Exception):
    pass


class Paused(Exception):
    """A sweep's job stops between points because its sweep pauses (the operator, an interlock): the
    job is parked (queued, out of the worker's queue) and the bench is free for other jobs until the
    sweep is resumed (service/runs/engine.py module doc)."""


def check_transition(table, current, target) -> None:
    if target not in table[current]:
        raise TransitionError(f"cannot go from {current.value} to {target.value}")


@dataclass
class _SweepControl:
    pause: threading.Event = field(default_factory=threading.Event)
    cancel: threading.Event = field(default_factory=threading.Event)
    parked_job: int | None = None  # the sweep's job while it is paused (not in the worker's queue)


class Engine:
    def __init__(
        self, storage: Storage, bench, settings: Settings, broker: EventBroker, recordings: RecordingStore | None = None
    ):
        self.storage, self.bench, self.settings, self.broker = storage, bench, settings, broker
        self.recordings = recordings  # raw recording of every identification (None: none kept)
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._controls: dict[int, _SweepControl] = {}
        self._job_cancel: dict[int, threading.Event] = {}
        self._lock = threading.RLock()  # state read-check-write of jobs and sweeps
        self._thread: threading.Thread | None = None
        self._shutdown = threading.Event()
        self._shutdown_reason = "service shut down"

    # --- lifecycle -----------------------------------------------------------------------------------
    def start(self, recover: bool = True) -> None:
        """`recover`: mark what a previous process left unfinished (only the process that owns the
        database's runs does this: a CLI run beside a server must not touch the server's work)."""
        if recover:
            self.recover()
        self._thread = threading.Thread(target=self._work, name="ripplecal-engine", daemon=True)
        self._thread.start()
        if recover and self.settings.engine.auto_resume:
            for sweep in self.storage.unfinished_sweeps():
                if sweep["state"] == SweepState.INTERRUPTED.value:
                    log.warning("engine.auto_resume: resuming sweep %s (%s)", sweep["id"], sweep["pause_reason"])
                    try:
                        self.resume_sweep(sweep["id"])
                    except TransitionError as exc:  # e.g. the drive faulted when we died: a person decides
                        log.warning("engine.auto_resume: sweep %s stays interrupted: %s", sweep["id"], exc)
                        self._set_sweep(
                            sweep["id"],
                            SweepState.INTERRUPTED,
                            pause_reason=f"{sweep['pause_reason']}; not resumed automatically: {exc}",
                        )

    def recover(self) -> None:
        """On start-up: what a previous process left unfinished. Jobs cannot still be running (failed,
        with the reason); sweeps become `interrupted` (not failed), resumable; a validation cut short
        keeps its points and says which LUT the drive was left holding."""
        held: dict[int, str] = {}
        for v in self.storage.running_validations():
            download = v["download"] or {}
            cells = v["cells"] or []
            lut = (
                f"the drive holds the LUT of map {download.get('map_id')} (CRC-32 {download.get('crc32')}) since this "
                "validation downloaded it"
            )
            error = f"the service stopped during this validation: {len(cells)} point(s) measured and kept; {lut}"
            self.storage.update_validation(v["id"], state="failed", error=error, finished_at=now_iso())
            held[v["job_id"]] = lut
        for job in self.storage.unfinished_jobs():
            why = "the service stopped while this job was " + job["state"]
            if job["sweep_id"] is not None:
                why += f"; its sweep {job['sweep_id']} is interrupted: resume it"
            if job["id"] in held:
                why += f"; {held[job['id']]}"
            self._set_job(job["id"], JobState.FAILED, error=why, finished_at=now_iso())
        for sweep in self.storage.unfinished_sweeps():
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES:
                reason = (
                    f"the service stopped while this sweep was {state.value} (no orderly shutdown: crash or "
                    f"kill); {sweep['done_points']} of {sweep['total_points']} points are stored, resume to "
                    "measure the rest"
                )
                self._set_sweep(sweep["id"], SweepState.INTERRUPTED, pause_reason=reason)

    def stop(self, reason: str | None = None, timeout_s: float = 30.0) -> None:
        """Orderly shutdown: the run in flight stops (bench left safe), unfinished sweeps become
        `interrupted` with `reason` (e.g. "service shut down (SIGTERM)") in their pause_reason."""
        if reason:
            self._shutdown_reason = reason
        self._shutdown.set()
        for ctl in list(self._controls.values()):
            ctl.cancel.set()
        for ev in list(self._job_cancel.values()):
            ev.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)
        for sweep in self.storage.unfinished_sweeps():
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES:
                self._set_sweep(
                    sweep["id"],
                    SweepState.INTERRUPTED,
                    pause_reason=f"{self._shutdown_reason} while this sweep was {state.value}; "
                    f"{sweep['done_points']} of {sweep['total_points']} points are stored",
                )

    # --- state writes (every one through the tables) ----------------------------------------------------------
    def _set_job(self, job_id: int, target: JobState, **fields) -> None:
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
        self._publish_job(job_id)

    def _set_sweep(self, sweep_id: int, target: SweepState, **fields) -> None:
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
        self._publish_sweep(sweep_id)

    def _set_state(self, what: str, table, states, read, update, target, fields: dict) -> None:
        """One state write through its table. Waits for a database that is unavailable (lock, read-only or
        full filesystem) until it takes the write or the service stops."""

        def write() -> None:
            with self._lock:
                current = states(read()["state"])
                if current != target:
                    check_transition(table, current, target)
                update(state=target.value, **fields)

        if not self._durably(write, f"{what}: state {target.value}"):
            raise StorageUnavailable("shutdown", f"{what}: state {target.value} not written (service stopping)")

    # --- submitting --------------------------------------------------------------------------------------
    def submit_identification(self, op: OperatingPoint, method: str, options) -> int:
        self.bench.check_reachable()  # refused now, not failed later
        check_limits(op, self.settings)  # refuse before anything is queued
        check_plant_time([op.speed_rpm], method, options, self.settings)
        job_id = self.storage.create_job(
            "identification", {"operating_point": op.model_dump(), "method": method, "options": options.model_dump()}
        )
        self._job_cancel[job_id] = threading.Event()
        self._queue.put(job_id)
        self._publish_job(job_id)
        return job_id

    def submit_sweep(self, grid: Grid, method: str, options, schedule_id: int | None = None, regime=None) -> int:
        """Queue a sweep over the planned grid: `grid` with the speeds `regime` (service.runs.plans.RegimePlacement)
        places around the predicted field-weakening onset (service.runs.plans.plan_grid, the grid POST
        /sweeps/preview shows). The planned grid is what the sweep stores, so its run and its map use the
        real axes."""
        self.bench.check_reachable()
        grid = plan_grid(grid, regime, self.settings).grid
        plan = SweepPlan.from_grid(grid)
        check_plant_time(grid.speed_rpm, method, options, self.settings)
        plan.dry_run(self.settings)  # every setpoint checked before the first frame
        sweep_id = self.storage.create_sweep(
            method,
            self.settings.identification.harmonic_order,
            grid.model_dump(),
            options.model_dump(),
            len(plan.points),
            self.bench.identity,
            __version__,
            schedule_id=schedule_id,
        )
        self._queue_sweep(sweep_id)
        return sweep_id

    def submit_validation(self, map_id: int, force: bool, options: ValidationOptions) -> int:
        """Queue the validation of a map in the drive's LUT mode (service.runs.validation). Refused before
        anything is queued: KeyError (no such map), ValidationRefused (no valid cell, partial without
        force), LimitError (a point outside the bench's limits)."""
        self.bench.check_reachable()
        row = self.storage.get_map(map_id)
        if row is None:
            raise KeyError(map_id)
        check_validatable(self.storage, map_id, force, fill=options.fill)
        check_points(row["axes"], self.settings)
        job_id = self.storage.create_job(
            "validation", {"map_id": map_id, "force": force, "options": options.model_dump()}
        )
        self._job_cancel[job_id] = threading.Event()
        self._queue.put(job_id)
        self._publish_job(job_id)
        return job_id

    def submit_refinement(self, map_id: int, request: RefineRequest) -> int:
        """Queue the refinement of a map (service/runs/refinement.py) as a sweep of kind `refinement`: its
        cells, pause, resume, cancel and crash-resume are a sweep's. Refused before anything is
        queued: KeyError (no such map), ValueError (method or options), LimitError (a validation point
        outside the bench's limits). A partial map is accepted: its non-ok cells are measured first.
        Returns the job's id."""
        self.bench.check_reachable()
        m = map_view(self.storage, map_id)
        if m is None:
            raise KeyError(map_id)
        check_request(request)
        options = parse_options(request.method, request.options)
        check_points(m.axes, self.settings)
        check_plant_time(m.axes["speed_rpm"], request.method, options, self.settings)
        not_ok = [[c.torque_nm, c.speed_rpm, c.udc_v] for c in m.cells if c.status != "ok"]
        state = {
            "target_db": request.target_db,
            "max_cells": request.max_cells,
            "validation": request.validation.model_dump(),
            "phase": "measure" if not_ok else "validate",
            "round": 0,
            "current_map_id": map_id,
            "axes": m.axes,
            "pending": not_ok,
            "cells_added": 0,
            "rounds": [],
            "stopped": None,
        }
        sweep_id = self.storage.create_sweep(
            request.method,
            m.harmonic_order,
            m.axes,
            options.model_dump(),
            len(not_ok),
            self.bench.identity,
            __version__,
            kind="refinement",
            source_map_id=map_id,
            refinement=state,
        )
        return self._queue_sweep(sweep_id)

    def _queue_sweep(self, sweep_id: int) -> int:
        kind = self.storage.get_sweep(sweep_id).get("kind") or "sweep"  # a refinement runs as a sweep of its kind
        job_id = self.storage.create_job(kind, {"sweep_id": sweep_id}, sweep_id=sweep_id)
        self._controls[sweep_id] = _SweepControl()
        self._job_cancel[job_id] = self._controls[sweep_id].cancel
        self._queue.put(job_id)
        self._publish_sweep(sweep_id)
        return job_id

    # --- controlling sweeps ---------------------------------------------------------------------------------
    def pause_sweep(self, sweep_id: int) -> None:
        """Pause takes effect between points: the run ends (bench made safe) and the sweep's job is parked,
        so other jobs run while it waits; resume queues it again."""
        with self._lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED)
            ctl = self._control(sweep_id)
            ctl.pause.set()
            if state == SweepState.QUEUED:
                self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
        self._publish_sweep(sweep_id)

    def resume_sweep(self, sweep_id: int) -> None:
        """Resume a paused sweep (its job is queued again: its next point is measured afresh, from a
        settled state), or one a previous service run left `interrupted` (queued again, it measures only
        the points not yet committed). Refused while an interlock is tripped."""
        with self._lock:
            state = self._sweep_state(sweep_id)
            if state not in (SweepState.PAUSED, SweepState.INTERRUPTED):
                raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused or interrupted")
            trip = self.bench.interlock_refusal()
            if trip is not None:
                raise TransitionError(
                    f"sweep {sweep_id} cannot resume: interlock tripped: {trip.reason}"
                    + ("; acknowledge it with POST /api/v1/bench/fault-reset" if trip.latched else "")
                )
            if state == SweepState.INTERRUPTED:
                self._set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None, finished_at=None)
                self._queue_sweep(sweep_id)
                return
            ctl = self._control(sweep_id)
            ctl.pause.clear()
            self._set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
            if ctl.parked_job is not None:
                job_id, ctl.parked_job = ctl.parked_job, None
                self._queue.put(job_id)
        self._publish_sweep(sweep_id)

    def cancel_sweep(self, sweep_id: int) -> None:
        with self._lock:
            try:
                state = self._sweep_state(sweep_id)
            except StorageUnavailable:
                if sweep_id in self._controls:
                    self._controls[sweep_id].cancel.set()  # the worker ends it when the database answers
                raise
            check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
            if state == SweepState.INTERRUPTED:
                self._set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
            else:
                ctl = self._control(sweep_id)
                ctl.cancel.set()
                sweep = self.storage.get_sweep(sweep_id)
                if ctl.parked_job is not None:
                    # paused with its job parked: nothing runs it, so it ends here with what it measured
                    job_id, ctl.parked_job = ctl.parked_job, None
                    map_id = (
                        build_map_from_sweep(self.storage, sweep_id)
                        if sweep["started_at"]
                        and sweep.get("kind", "sweep") == "sweep"
                        and self.storage.sweep_results(sweep_id)
                        else sweep["map_id"]
                    )
                    self._set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso(), map_id=map_id)
                    self._set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
                elif state in (SweepState.QUEUED, SweepState.PAUSED) and not sweep["started_at"]:
                    self._set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
        self._publish_sweep(sweep_id)

    def cancel_job(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        if job is None:
            raise KeyError(job_id)
        check_transition(JOB_TRANSITIONS, JobState(job["state"]), JobState.CANCELLED)
        if job["sweep_id"] is not None:
            return self.cancel_sweep(job["sweep_id"])
        self._job_cancel.setdefault(job_id, threading.Event()).set()
        if job["state"] == "queued":
            self._set_job(job_id, JobState.CANCELLED, finished_at=now_iso())

    def _sweep_state(self, sweep_id: int) -> SweepState:
        sweep = self.storage.get_sweep(sweep_id)
        if sweep is None:
            raise KeyError(sweep_id)
        return SweepState(sweep["state"])

    def _control(self, sweep_id: int) -> _SweepControl:
        ctl = self._controls.get(sweep_id)
        if ctl is None:  # a paused/queued sweep always has one in this process (others are interrupted)
            raise TransitionError(f"sweep {sweep_id} is not run by this service process")
        return ctl

    # --- the worker ------------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job_id = self._queue.get()
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

    def _work_on(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        if job is None or job["state"] != "queued":
            return
        cancel = self._job_cancel.setdefault(job_id, threading.Event())
        if self._shutdown.is_set():
            self._set_job(
                job_id, JobState.FAILED, error=f"{self._shutdown_reason} before this job ran", finished_at=now_iso()
            )
            return
        if cancel.is_set():
            self._set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
            return
        self._set_job(job_id, JobState.RUNNING, started_at=now_iso())
        try:
            if job["kind"] == "identification":
                self._run_identification(job_id, job)
            elif job["kind"] == "validation":
                self._run_validation(job_id, job)
            elif job["kind"] == "refinement":
                self._run_refinement(job_id, job["sweep_id"])
            else:
                self._run_sweep(job_id, job["sweep_id"])
            final = JobState.CANCELLED if cancel.is_set() else JobState.DONE
            self._set_job(
                job_id, final, finished_at=now_iso(), error=self._shutdown_reason if self._shutdown.is_set() else None
            )
        except Paused:
            self._park(job_id, job["sweep_id"])
        except Cancelled:
            self._set_job(
                job_id,
                JobState.CANCELLED,
                finished_at=now_iso(),
                error=self._shutdown_reason if self._shutdown.is_set() else None,
            )
        except Exception as exc:
            error = _error_text(exc)
            if isinstance(exc, EXPECTED_FAILURES):
                log.warning("job %s failed: %s", job_id, error)  # the bench said no: one line, no traceback
            else:
                log.error("job %s failed: %s", job_id, traceback.format_exc())
            self._set_job(job_id, JobState.FAILED, error=error, finished_at=now_iso())
            sweep = self.storage.get_sweep(job["sweep_id"]) if job["sweep_id"] is not None else None
            if sweep is not None and SweepState(sweep["state"]) not in (
                SweepState.CANCELLED,
                SweepState.DONE,
                SweepState.FAILED,
            ):
                self._set_sweep(job["sweep_id"], SweepState.FAILED, error=error, finished_at=now_iso())
        self._publish_job(job_id)

    def _park(self, job_id: int, sweep_id: int) -> None:
        """The sweep paused between points: its job waits, queued but out of the worker's queue, until
        resume puts it back (or cancel ends it); the worker goes on with the next job."""
        with self._lock:
            ctl = self._controls[sweep_id]
            if SweepState(self.storage.get_sweep(sweep_id)["state"]) != SweepState.PAUSED:
                self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
            self._set_job(job_id, JobState.QUEUED)
            if ctl.pause.is_set():
                ctl.parked_job = job_id
            else:  # resumed while the run was ending: straight back into the queue
                self._set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
                self._queue.put(job_id)
        log.info("sweep %s paused: its job %s waits; the bench is free for other jobs", sweep_id, job_id)

    def _run_identification(self, job_id: int, job: dict) -> None:
        req = job["request"]
        op = OperatingPoint.model_validate(req["operating_point"])
        options = parse_options(req["method"], req["options"])
        started = now_iso()
        recorder = self._new_recorder()
        try:
            result = identify_at(
                self.bench,
                self.settings,
                op,
                req["method"],
                options,
                cancel=self._job_cancel[job_id],
                progress=lambda w: self._publish_window(job_id, w),
                recorder=recorder,
            )
        except Exception as exc:
            if self._job_cancel[job_id].is_set() and not isinstance(exc, InterlockTripped):
                _discard(recorder)
                raise Cancelled() from exc
            row = result_row(
                op,
                req["method"],
                options,
                self.bench.identity,
                started,
                error=_error_text(exc),
                job_id=job_id,
                harmonic_order=self.settings.identification.harmonic_order,
            )
            rid = self._insert_result(row, recorder)
            self.storage.update_job(job_id, result_id=rid)
            raise
        row = result_row(
            op,
            req["method"],
            options,
            self.bench.identity,
            started,
            result,
            job_id=job_id,
            harmonic_order=result.harmonic_order,
        )
        stored: dict = {}
        # the bench is safe (the run has ended): a database that cannot take the result now is waited for
        self._durably(lambda: stored.setdefault("id", self._insert_result(row, recorder)), f"job {job_id}: its result")
        if "id" in stored:
            self._durably(lambda: self.storage.update_job(job_id, result_id=stored["id"]), f"job {job_id}: its result")

    def _new_recorder(self) -> RunRecorder | None:
        return self.recordings.recorder() if self.recordings is not None else None

    def _insert_result(self, row: dict, recorder: RunRecorder | None) -> int:
        """Store the result, then write its raw recording: a recording that fails is noted in the
        stored row and never loses the result."""
        rid = self.storage.insert_result(row)
        if self.recordings is not None:
            self.recordings.keep(recorder, rid, row)
        return rid

    def _run_validation(self, job_id: int, job: dict) -> None:
        """Download, then every point; the validation is stored however it ends (the map keeps its
        latest). An interlock trip or a point's stop fails the job with the reason; a cancel cancels it.
        The bench is made safe after every point (bench.operating_point)."""
        req = job["request"]
        options = ValidationOptions.model_validate(req["options"])

        def on_cell(cell: dict, total: int) -> None:
            self.broker.publish("job.progress", {"job_id": job_id, "kind": "validation", "total": total, "cell": cell})

        run = run_validation(
            self.storage,
            self.bench,
            self.settings,
            req["map_id"],
            req["force"],
            options,
            self._job_cancel[job_id],
            on_cell=on_cell,
            on_progress=lambda r: store_validation(self.storage, job_id, r, self.bench.identity, finished=False),
        )
        store_validation(self.storage, job_id, run, self.bench.identity)
        if run.state == "cancelled":
            raise Cancelled()
        if run.state == "failed":
            raise ValidationStopped(run.error)

    def _run_sweep(self, job_id: int, sweep_id: int) -> None:
        """The sweep as continuous bench runs (service/bench/run.py): the drive stays enabled and the
        load turning from point to point; a run ends (bench made safe) on pause, cancel, an interlock
        trip, a failure of the bench itself, and at the end. A point that cannot be measured is stored
        failed and the run goes on; an interlock trip discards the point in flight and pauses.
        Two passes: every point, then once more each point whose result is not ok, with what its
        neighbours now know on every side (service/maps/neighbours.py); a cell that stays non-ok gets the fill
        rule's entry in the map (service/maps/fill.py)."""
        sweep = self.storage.get_sweep(sweep_id)
        ctl = self._controls[sweep_id]
        grid = Grid.model_validate(sweep["grid"])
        options = parse_options(sweep["method"], sweep["options"])
        plan = SweepPlan.from_grid(grid)
        done = self.storage.committed_points(sweep_id)  # a resumed sweep measures only the rest
        if ctl.cancel.is_set() or SweepState(sweep["state"]) == SweepState.CANCELLED:
            raise Cancelled()  # cancelled as the worker took it: nothing was run
        if ctl.pause.is_set():
            raise Paused()  # paused while it waited in the queue
        self._set_sweep(sweep_id, SweepState.RUNNING, started_at=sweep["started_at"] or now_iso(), pause_reason=None)
        first = [op for op in plan.points if (op.torque_nm, op.speed_rpm, op.udc_v) not in done]
        in_flight = self._measure_points(sweep_id, sweep, ctl, grid, options, first, sweep_pass=1)
        if in_flight is None and not ctl.cancel.is_set() and not self._shutdown.is_set():
            again = second_pass_points(plan, self.storage.sweep_results(sweep_id))
            if again:
                log.info(
                    "sweep %s: %d point(s) not ok measured once more with their neighbours' priors",
                    sweep_id,
                    len(again),
                )
                in_flight = self._measure_points(sweep_id, sweep, ctl, grid, options, again, sweep_pass=2)
        if self._shutdown.is_set():
            s = self.storage.get_sweep(sweep_id)
            where = f" during point {in_flight.label()} (measured again on resume)" if in_flight is not None else ""
            self._set_sweep(
                sweep_id,
                SweepState.INTERRUPTED,
                pause_reason=f"{self._shutdown_reason}{where}; {s['done_points']} of {s['total_points']} "
                "points are stored",
            )
            return
        map_id = build_map_from_sweep(self.storage, sweep_id)
        final = SweepState.CANCELLED if ctl.cancel.is_set() else SweepState.DONE
        self._set_sweep(sweep_id, final, finished_at=now_iso(), map_id=map_id)

    def _measure_points(
        self,
        sweep_id: int,
        sweep: dict,
        ctl: "_SweepControl",
        grid: Grid,
        options,
        points: list[OperatingPoint],
        sweep_pass: int,
        neighbour_rows: Callable[[], list[dict]] | None = None,
        tags: dict | None = None,
    ) -> OperatingPoint | None:
        """Measure `points` in continuous runs (see _run_sweep), holding while paused. Returns the point
        in flight when a cancel or a shutdown stopped it (None when every point was measured or the
        stop came between points). Priors come from `neighbour_rows()` (default: the sweep's current
        results); `tags` go into every result's details."""
        neighbour_rows = neighbour_rows or (lambda: self.storage.sweep_results(sweep_id))
        tags = {"sweep_pass": sweep_pass, **(tags or {})}
        if options.stop_margin_db is None:  # a cell meant for a LUT: identified to a margin below its target
            options = options.model_copy(update={"stop_margin_db": LUT_MARGIN_DB})
        point = _PointInFlight()
        i = 0
        while i < len(points):
            if ctl.cancel.is_set():
                break
            if ctl.pause.is_set():
                raise Paused()
            try:
                with self.bench.run(cancel=ctl.cancel, **run_settings(self.settings, options)) as run:
                    while i < len(points) and not ctl.pause.is_set() and not ctl.cancel.is_set():
                        point.start(points[i], self._new_recorder())
                        try:
                            prior = prior_from_neighbours(point.op, neighbour_rows(), grid.model_dump())
                            result = identify_in_run(
                                run,
                                self.settings,
                                point.op,
                                sweep["method"],
                                options,
                                prior=prior,
                                recorder=point.recorder,
                            )
                            result.details.update(tags)
                            row = result_row(
                                point.op,
                                sweep["method"],
                                options,
                                self.bench.identity,
                                point.started,
                                result,
                                sweep_id=sweep_id,
                                harmonic_order=result.harmonic_order,
                            )
                        except (MeasurementError, LimitError) as exc:
                            # this point could not be measured; the bench is fine: the run goes on
                            log.warning("sweep %s point %s failed: %s", sweep_id, point.op.label(), exc)
                            row = self._failed_row(point, sweep, options, exc, sweep_id, tags)
                        point.row = row  # measured: kept if the database cannot take it now
                        self._store_point(sweep_id, point.op, row, point.recorder)
                        point.clear()
                        i += 1
            except StorageUnavailable as exc:
                # the run has ended (bench made safe); the point measured is kept and written when the
                # database answers again, or measured again if it was not measured yet
                self._storage_pause(sweep_id, ctl, exc, point)
                if point.row is not None:  # stored now
                    i += 1
                point.clear()
                continue
            except InterlockTripped as exc:
                # the point is measured again after the operator resumes; its attempt (if any
                # torque was commanded) is kept as a failed, discarded attempt, never ok
                if point.op is not None and not exc.refused:
                    self._store_point(
                        sweep_id,
                        point.op,
                        self._discarded_row(point.op, sweep, options, point.started, exc, sweep_id),
                        point.recorder,
                    )
                else:
                    _discard(point.recorder)
                self._pause_for_interlock(sweep_id, ctl, point.op or points[min(i, len(points) - 1)], exc)
                point.clear()
                continue
            except Exception as exc:
                if ctl.cancel.is_set():
                    _discard(point.recorder)
                    return point.op
                if point.op is None:
                    raise  # the run itself could not start or end (bench not safe): the sweep fails
                # the bench failed during this point (the run ended, bench made safe): stored failed, next point
                log.warning("sweep %s point %s failed: %s", sweep_id, point.op.label(), exc)
                self._store_point(
                    sweep_id, point.op, self._failed_row(point, sweep, options, exc, sweep_id, tags), point.recorder
                )
                point.clear()
                i += 1
        return None

    def _failed_row(
        self, point: "_PointInFlight", sweep, options, exc: BaseException, sweep_id: int, tags: dict
    ) -> dict:
        return result_row(
            point.op,
            sweep["method"],
            options,
            self.bench.identity,
            point.started,
            error=_error_text(exc),
            sweep_id=sweep_id,
            harmonic_order=self.settings.identification.harmonic_order,
            detail={"message": _error_text(exc), "details": dict(tags)},
        )

    # --- refinements ---------------------------------------------------------------------------------------
    def _run_refinement(self, job_id: int, sweep_id: int) -> None:
        """A refinement's rounds (service/runs/refinement.py): measure the pending cells, build the refined map,
        validate it in the drive's LUT mode, plan the next cells; its state is saved after every step,
        so a resume (after a pause, an interlock or a crash) goes on from where it stood."""
        sweep = self.storage.get_sweep(sweep_id)
        ctl = self._controls[sweep_id]
        state = sweep["refinement"]
        options = parse_options(sweep["method"], sweep["options"])
        if ctl.cancel.is_set() or SweepState(sweep["state"]) == SweepState.CANCELLED:
            raise Cancelled()
        if ctl.pause.is_set():
            raise Paused()
        self._set_sweep(sweep_id, SweepState.RUNNING, started_at=sweep["started_at"] or now_iso(), pause_reason=None)
        source = self.storage.get_map(sweep["source_map_id"])
        while state["phase"] != "done":
            if ctl.cancel.is_set():
                break
            if ctl.pause.is_set():
                raise Paused()
            if state["phase"] == "measure":
                self._refinement_measure(sweep_id, sweep, ctl, options, state, source)
            else:
                self._refinement_validate(job_id, sweep_id, ctl, state)
            self._save_refinement(sweep_id, state)
        if self._shutdown.is_set():
            self._set_sweep(
                sweep_id,
                SweepState.INTERRUPTED,
                pause_reason=f"{self._shutdown_reason} during round {state['round']} ({state['phase']}); "
                "resume to go on from there",
            )
            return
        final = SweepState.CANCELLED if ctl.cancel.is_set() else SweepState.DONE
        self._set_sweep(sweep_id, final, finished_at=now_iso(), map_id=state["current_map_id"])

    def _refinement_rows(self, sweep_id: int, source: dict) -> list[dict]:
        """The source map's results, then the refinement's own (a later one for the same cell wins)."""
        ids = [c["result_id"] for c in source["cells"] if c["result_id"] is not None]
        return list(self.storage.results_by_id(ids).values()) + self.storage.sweep_results(sweep_id)

    def _refinement_measure(
        self, sweep_id: int, sweep: dict, ctl: "_SweepControl", options, state: dict, source: dict
    ) -> None:
        """Identify the round's pending cells (those not yet measured in this round), then build the
        refined map from every result and move on to its validation."""
        measured = {
            (r["torque_nm"], r["speed_rpm"], r["udc_v"])
            for r in self.storage.sweep_results(sweep_id)
            if ((r.get("detail") or {}).get("details") or {}).get("refinement_round") == state["round"]
        }
        points = [
            OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u)
            for t, n, u in state["pending"]
            if (t, n, u) not in measured
        ]
        grid = Grid(**state["axes"])
        self._publish_refinement(sweep_id, state, f"measuring {len(points)} cell(s)")
        self._measure_points(
            sweep_id,
            sweep,
            ctl,
            grid,
            options,
            points,
            sweep_pass=1,
            neighbour_rows=lambda: self._refinement_rows(sweep_id, source),
            tags={"refinement_round": state["round"]},
        )
        if ctl.cancel.is_set():
            return
        state["cells_added"] += len(state["pending"])  # the round's cells, also those measured before a crash
        provenance = {
            "refinement_id": sweep_id,
            "source_map_id": sweep["source_map_id"],
            "round": state["round"],
            "cells_added": state["cells_added"],
        }
        state["current_map_id"] = build_map(
            self.storage,
            state["axes"],
            self._refinement_rows(sweep_id, source),
            sweep_id,
            sweep["harmonic_order"],
            sweep["method"],
            self.bench.identity,
            refined_from=sweep["source_map_id"],
            provenance=provenance,
        )
        state["phase"] = "validate"

    def _refinement_validate(self, job_id: int, sweep_id: int, ctl: "_SweepControl", state: dict) -> None:
        """Validate the current map in the drive's LUT mode; plan the next round, or end."""
        map_id = state["current_map_id"]
        self._publish_refinement(sweep_id, state, f"validating map {map_id}")

        def on_cell(cell: dict, total: int) -> None:
            self.broker.publish(
                "job.progress",
                {"job_id": job_id, "kind": "refinement", "round": state["round"], "total": total, "cell": cell},
            )

        run = run_validation(
            self.storage,
            self.bench,
            self.settings,
            map_id,
            True,
            ValidationOptions.model_validate(state["validation"]),
            ctl.cancel,
            on_cell=on_cell,
            on_progress=lambda r: store_validation(self.storage, job_id, r, self.bench.identity, finished=False),
        )
        validation_id = store_validation(self.storage, job_id, run, self.bench.identity)
        if run.state == "cancelled":
            return
        if run.state == "failed":
            # an interlock stopped it: pause like a sweep; on resume the map is validated again
            with self._lock:
                ctl.pause.set()
                self._set_sweep(
                    sweep_id,
                    SweepState.PAUSED,
                    pause_reason=f"{run.error} (validating refined map "
                    f"{map_id}); acknowledge with POST /api/v1/bench/fault-reset, then resume",
                )
            return
        m = map_view(self.storage, map_id)
        plan = plan_round(
            m.axes,
            [c.model_dump() for c in m.cells],
            run.cells,
            state["target_db"],
            state["max_cells"] - state["cells_added"],
        )
        summary = run.summary()
        state["rounds"].append(
            {
                "round": state["round"],
                "map_id": map_id,
                "validation_id": validation_id,
                "points": len(run.cells),
                "below_target": plan.failing,
                "grid_median_db": summary["grid"]["median_db"],
                "midpoint_median_db": summary["midpoint"]["median_db"],
                "min_db": min(
                    (x for x in (summary["grid"]["min_db"], summary["midpoint"]["min_db"]) if x is not None),
                    default=None,
                ),
                "inserted": plan.inserted,
                "remeasured": len(plan.remeasure),
                "new_cells": len(plan.new_cells),
            }
        )
        if plan.failing == 0:
            state["phase"], state["stopped"] = "done", None
        elif not plan.cells:
            state["phase"] = "done"
            state["stopped"] = f"{plan.failing} point(s) still below {state['target_db']:g} dB: " + (
                "; ".join(plan.reasons) or "nothing left to insert"
            )
        elif state["round"] + 1 >= MAX_ROUNDS:
            state["phase"] = "done"
            state["stopped"] = (
                f"{plan.failing} point(s) still below {state['target_db']:g} dB after {MAX_ROUNDS} rounds"
            )
        else:
            state["axes"] = axes_with(m.axes, plan.inserted)
            state["pending"] = [list(k) for k in plan.cells]
            state["round"] += 1
            state["phase"] = "measure"

    def _save_refinement(self, sweep_id: int, state: dict) -> None:
        # total: the cells planned so far (those measured, and the round's pending ones)
        total = state["cells_added"] + (len(state["pending"]) if state["phase"] == "measure" else 0)
        self.storage.update_sweep(
            sweep_id, refinement=state, grid=state["axes"], map_id=state["current_map_id"], total_points=total
        )
        self._publish_refinement(sweep_id, state, state["phase"])

    def _publish_refinement(self, sweep_id: int, state: dict, what: str) -> None:
        self.broker.publish(
            "refinement.progress",
            {
                "sweep_id": sweep_id,
                "round": state["round"],
                "phase": state["phase"],
                "what": what,
                "map_id": state["current_map_id"],
                "cells_added": state["cells_added"],
            },
        )

    def _store_point(self, sweep_id: int, op: OperatingPoint, row: dict, recorder: RunRecorder | None) -> None:
        rid = self._insert_result(row, recorder)
        # the result by its id: the API's event stream shows it as a result (service/api/routes/events.py)
        self.broker.publish(
            "sweep.point",
            {"sweep_id": sweep_id, "operating_point": op.model_dump(), "state": row["status"], "result_id": rid},
        )
        self._publish_sweep(sweep_id)

    def _discarded_row(self, op, sweep, options, started, exc: InterlockTripped, sweep_id: int) -> dict:
        return result_row(
            op,
            sweep["method"],
            options,
            self.bench.identity,
            started,
            error=_error_text(exc),
            sweep_id=sweep_id,
            harmonic_order=self.settings.identification.harmonic_order,
            detail={"message": str(exc), "discarded": "interlock", "interlock": exc.trip.public()},
        )

    def _storage_pause(
        self, sweep_id: int, ctl: "_SweepControl", exc: StorageUnavailable, point: "_PointInFlight"
    ) -> None:
        """The database cannot be used: the bench is already safe (the run ended). Tell the dashboard the
        sweep waits (in memory: the database cannot take it), keep the point measured and write it when the
        database answers again, then go on by itself. A cancel or a shutdown ends the wait."""
        reason = f"{exc.public} at {now_iso()}; " + (
            f"the point {point.op.label()} is kept and written when it answers again"
            if point.row is not None
            else "the sweep goes on when it answers again"
        )
        log.warning("sweep %s waits for the database: %s", sweep_id, reason)
        self.broker.publish(
            "sweep.progress",
            {
                "sweep_id": sweep_id,
                "state": "paused",
                "pause_reason": reason,
                "storage": {"cause": exc.cause, "retry_after_s": exc.retry_after_s},
            },
        )
        if point.row is not None:
            # kept even through a cancel: a point measured is never thrown away while the service runs
            stored = self._durably(
                lambda: self._store_point(sweep_id, point.op, point.row, point.recorder),
                f"sweep {sweep_id}: storing point {point.op.label()}",
            )
            if not stored:
                _discard(point.recorder)
                point.row = None
        else:
            _discard(point.recorder)
            self._durably(lambda: self.storage.get_sweep(sweep_id), f"sweep {sweep_id}: the database", ctl.cancel)
        self._publish_sweep(sweep_id)

    def _durably(self, write: Callable[[], object], what: str, cancel: threading.Event | None = None) -> bool:
        """Call `write` until the database takes it (backoff STORAGE_RETRY_S, doubling to the last); False
        if a cancel or the shutdown ended the wait first. Only ever called with the bench safe."""
        pause = STORAGE_RETRY_S[0]
        while True:
            try:
                write()
                return True
            except StorageUnavailable as exc:
                if threading.current_thread() is not self._thread:
                    raise  # an API request is answered at once (503), never held
                if self._shutdown.is_set() or (cancel is not None and cancel.is_set()):
                    log.warning(
                        "%s: given up (%s): %s", what, "shutdown" if self._shutdown.is_set() else "cancelled", exc
                    )
                    return False
                log.info("%s: the database is unavailable (%s); next try in %.1f s", what, exc.cause, pause)
                self._shutdown.wait(pause)
                pause = min(2 * pause, STORAGE_RETRY_S[1])

    def _pause_for_interlock(
        self, sweep_id: int, ctl: _SweepControl, op: OperatingPoint, exc: InterlockTripped
    ) -> None:
        reason = (
            f"{exc.trip.reason} during point {op.label()}"
            + (" (refused before it started)" if exc.refused else " (discarded; measured again on resume)")
            + (
                "; acknowledge with POST /api/v1/bench/fault-reset, then resume"
                if exc.trip.latched
                else "; resume when it has cleared"
            )
        )
        with self._lock:
            ctl.pause.set()
            self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason=reason)
        log.warning("sweep %s paused: %s", sweep_id, reason)
        self._publish_sweep(sweep_id)

    # --- events ----------------------------------------------------------------------------------------------
    def _publish_job(self, job_id: int) -> None:
        try:
            job = self.storage.get_job(job_id)
        except StorageUnavailable:
            return  # the dashboard hears of it when the database answers again
        self.broker.publish(
            "job.state", {"job_id": job_id, "state": job["state"], "kind": job["kind"], "error": job["error"]}
        )

    def _publish_window(self, job_id: int, window) -> None:
        """A run's accepted window as it comes (plant time on the DAQ clock, residual in full scale)."""
        self.broker.publish(
            "job.progress",
            {
                "job_id": job_id,
                "plant_time_s": window.end_time_s,
                "residual_fs": window.phasor.amplitude,
                "noise_std_fs": window.noise_std_fs,
            },
        )

    def _publish_sweep(self, sweep_id: int) -> None:
        try:
            s = self.storage.get_sweep(sweep_id)
        except StorageUnavailable:
            return
        self.broker.publish(
            "sweep.progress",
            {
                "sweep_id": sweep_id,
                "kind": s.get("kind") or "sweep",
                "state": s["state"],
                "done": s["done_points"],
                "total": s["total_points"],
                "map_id": s["map_id"],
                "pause_reason": s["pause_reason"],
            },
        )


def second_pass_points(plan: SweepPlan, current: list[dict]) -> list[OperatingPoint]:
    """The plan's points, in its order, whose current result is not ok and was not itself measured in
    the second pass (a resumed sweep does not measure a point a third time)."""
    again = set()
    for row in current:
        details = (row.get("detail") or {}).get("details") or {}
        if row["status"] != "ok" and details.get("sweep_pass") != 2:
            again.add((row["torque_nm"], row["speed_rpm"], row["udc_v"]))
    return [op for op in plan.points if (op.torque_nm, op.speed_rpm, op.udc_v) in again]


class _PointInFlight:
    """The sweep point being measured: its operating point, start time and raw recorder."""

    def __init__(self) -> None:
        self.clear()

    def start(self, op: OperatingPoint, recorder: RunRecorder | None) -> None:
        self.op, self.recorder, self.started, self.row = op, recorder, now_iso(), None

    def clear(self) -> None:
        self.op: OperatingPoint | None = None
        self.recorder: RunRecorder | None = None
        self.started: str | None = None
        self.row: dict | None = None  # its result, once measured (until stored)


def _discard(recorder: RunRecorder | None) -> None:
    """A run that leaves no result (cancelled, refused) leaves no recording either."""
    if recorder is not None:
        recorder.close()


def _error_text(exc: BaseException) -> str:
    """'Type: message' plus any notes (e.g. what failed after an interlock trip)."""
    text = f"{type(exc).__name__}: {exc}"
    notes = getattr(exc, "__notes__", None)
    return text + "".join(f"; {n}" for n in notes) if notes else text
