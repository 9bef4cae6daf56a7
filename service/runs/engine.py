"""The run engine: one worker thread owns the bench and runs queued jobs one at a time.

The state machines are tables (service/runs/states.py); every state write goes through `set_job` /
`set_sweep`, which check the table; any other transition is a bug and raises. The engine owns the
queue, the worker, submitting, pause / resume / cancel and recovery; a sweep's run body (its points,
the second pass, its map; a refinement's rounds) is service/runs/sweep_run.py, which calls back only
through the engine's RunHost methods. Pause takes effect between points: the run ends (bench safe)
and the sweep's job is parked (queued, out of the worker's queue), so other jobs run while the sweep
waits; resume queues it again. Cancel acts between points or inside a measurement; the bench is left
safe (torque off, injection off) in every case.

Surviving the night: a sweep the service stopped under (crash, kill -9, shutdown) is `interrupted`
when the service starts again; resume (or `engine.auto_resume`) measures only the points not yet
committed, and each point keeps one current result (earlier attempts are history:
results.superseded_by). A database that cannot be used is waited for (`durably`), with the bench safe.
"""

from __future__ import annotations

import logging
import queue
import threading
import traceback
from typing import Callable

from drivers.errors import DriverError
from service import __version__
from service.bench.bench import BenchError
from service.bench.interlocks import InterlockTripped
from service.bench.setpoint_accounting import AccountingError
from service.identification.session import MeasurementError
from service.maps.build import build_map_from_sweep
from service.maps.view import map_view
from service.model.limits import LimitError, check_limits
from service.model.operating_point import OperatingPoint
from service.runs.events import EventBroker
from service.runs.identify import check_plant_time, identify_at, parse_options
from service.runs.plans import Grid, SweepPlan, plan_grid
from service.runs.refinement import RefineRequest, check_request
from service.runs.states import (
    JOB_TRANSITIONS,
    SWEEP_TRANSITIONS,
    UNFINISHED_SWEEP_STATES,
    Cancelled,
    JobState,
    Paused,
    SweepControl,
    SweepState,
    TransitionError,
    check_transition,
)
from service.runs.sweep_run import SweepRunner, discard_recorder, error_text
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


STORAGE_RETRY_S = (0.5, 10.0)  # first and longest pause between tries of a database that is unavailable


class Engine:
    def __init__(
        self, storage: Storage, bench, settings: Settings, broker: EventBroker, recordings: RecordingStore | None = None
    ):
        self.storage, self.bench, self.settings, self.broker = storage, bench, settings, broker
        self.recordings = recordings  # raw recording of every identification (None: none kept)
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._controls: dict[int, SweepControl] = {}
        self._job_cancel: dict[int, threading.Event] = {}
        self._lock = threading.RLock()  # state read-check-write of jobs and sweeps
        self._thread: threading.Thread | None = None
        self._shutdown = threading.Event()
        self._shutdown_reason = "service shut down"
        self._sweeps = SweepRunner(self)  # a sweep's and a refinement's run body (service/runs/sweep_run.py)

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
            for sweep in self.storage.unfinished_sweeps():
                if sweep["state"] == SweepState.INTERRUPTED.value:
                    log.warning("engine.auto_resume: resuming sweep %s (%s)", sweep["id"], sweep["pause_reason"])
                    try:
                        self.resume_sweep(sweep["id"])
                    except TransitionError as exc:  # e.g. the drive faulted when we died: a person decides
                        log.warning("engine.auto_resume: sweep %s stays interrupted: %s", sweep["id"], exc)
                        self.set_sweep(
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
            self.set_job(job["id"], JobState.FAILED, error=why, finished_at=now_iso())
        for sweep in self.storage.unfinished_sweeps():
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES:
                reason = (
                    f"the service stopped while this sweep was {state.value} (no orderly shutdown: crash or "
                    f"kill); {sweep['done_points']} of {sweep['total_points']} points are stored, resume to "
                    "measure the rest"
                )
                self.set_sweep(sweep["id"], SweepState.INTERRUPTED, pause_reason=reason)

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
                self.set_sweep(
                    sweep["id"],
                    SweepState.INTERRUPTED,
                    pause_reason=f"{self._shutdown_reason} while this sweep was {state.value}; "
                    f"{sweep['done_points']} of {sweep['total_points']} points are stored",
                )

    # --- state writes (every one through the tables) ----------------------------------------------------------
    def set_job(self, job_id: int, target: JobState, **fields) -> None:
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

    def set_sweep(self, sweep_id: int, target: SweepState, **fields) -> None:
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

    def _set_state(self, what: str, table, states, read, update, target, fields: dict) -> None:
        """One state write through its table. Waits for a database that is unavailable (lock, read-only or
        full filesystem) until it takes the write or the service stops."""

        def write() -> None:
            with self._lock:
                current = states(read()["state"])
                if current != target:
                    check_transition(table, current, target)
                update(state=target.value, **fields)

        if not self.durably(write, f"{what}: state {target.value}"):
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
        self._controls[sweep_id] = SweepControl()
        self._job_cancel[job_id] = self._controls[sweep_id].cancel
        self._queue.put(job_id)
        self.publish_sweep(sweep_id)
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
                self.set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
        self.publish_sweep(sweep_id)

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
                self.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None, finished_at=None)
                self._queue_sweep(sweep_id)
                return
            ctl = self._control(sweep_id)
            ctl.pause.clear()
            self.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
            if ctl.parked_job is not None:
                job_id, ctl.parked_job = ctl.parked_job, None
                self._queue.put(job_id)
        self.publish_sweep(sweep_id)

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
                self.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
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
                    self.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso(), map_id=map_id)
                    self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
                elif state in (SweepState.QUEUED, SweepState.PAUSED) and not sweep["started_at"]:
                    self.set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
        self.publish_sweep(sweep_id)

    def cancel_job(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        if job is None:
            raise KeyError(job_id)
        check_transition(JOB_TRANSITIONS, JobState(job["state"]), JobState.CANCELLED)
        if job["sweep_id"] is not None:
            return self.cancel_sweep(job["sweep_id"])
        self._job_cancel.setdefault(job_id, threading.Event()).set()
        if job["state"] == "queued":
            self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())

    def _sweep_state(self, sweep_id: int) -> SweepState:
        sweep = self.storage.get_sweep(sweep_id)
        if sweep is None:
            raise KeyError(sweep_id)
        return SweepState(sweep["state"])

    def _control(self, sweep_id: int) -> SweepControl:
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
            self.set_job(
                job_id, JobState.FAILED, error=f"{self._shutdown_reason} before this job ran", finished_at=now_iso()
            )
            return
        if cancel.is_set():
            self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
            return
        self.set_job(job_id, JobState.RUNNING, started_at=now_iso())
        try:
            if job["kind"] == "identification":
                self._run_identification(job_id, job)
            elif job["kind"] == "validation":
                self._run_validation(job_id, job)
            elif job["kind"] == "refinement":
                self._sweeps.run_refinement(job_id, job["sweep_id"], self._controls[job["sweep_id"]])
            else:
                self._sweeps.run_sweep(job_id, job["sweep_id"], self._controls[job["sweep_id"]])
            final = JobState.CANCELLED if cancel.is_set() else JobState.DONE
            self.set_job(
                job_id, final, finished_at=now_iso(), error=self._shutdown_reason if self._shutdown.is_set() else None
            )
        except Paused:
            self._park(job_id, job["sweep_id"])
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
                self.set_sweep(job["sweep_id"], SweepState.FAILED, error=error, finished_at=now_iso())
        self._publish_job(job_id)

    def _park(self, job_id: int, sweep_id: int) -> None:
        """The sweep paused between points: its job waits, queued but out of the worker's queue, until
        resume puts it back (or cancel ends it); the worker goes on with the next job."""
        with self._lock:
            ctl = self._controls[sweep_id]
            if SweepState(self.storage.get_sweep(sweep_id)["state"]) != SweepState.PAUSED:
                self.set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
            self.set_job(job_id, JobState.QUEUED)
            if ctl.pause.is_set():
                ctl.parked_job = job_id
            else:  # resumed while the run was ending: straight back into the queue
                self.set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None)
                self._queue.put(job_id)
        log.info("sweep %s paused: its job %s waits; the bench is free for other jobs", sweep_id, job_id)

    def _run_identification(self, job_id: int, job: dict) -> None:
        req = job["request"]
        op = OperatingPoint.model_validate(req["operating_point"])
        options = parse_options(req["method"], req["options"])
        started = now_iso()
        recorder = self.new_recorder()
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
                discard_recorder(recorder)
                raise Cancelled() from exc
            row = result_row(
                op,
                req["method"],
                options,
                self.bench.identity,
                started,
                error=error_text(exc),
                job_id=job_id,
                harmonic_order=self.settings.identification.harmonic_order,
            )
            rid = self.insert_result(row, recorder)
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
        self.durably(lambda: stored.setdefault("id", self.insert_result(row, recorder)), f"job {job_id}: its result")
        if "id" in stored:
            self.durably(lambda: self.storage.update_job(job_id, result_id=stored["id"]), f"job {job_id}: its result")

    def new_recorder(self) -> RunRecorder | None:
        return self.recordings.recorder() if self.recordings is not None else None

    def insert_result(self, row: dict, recorder: RunRecorder | None) -> int:
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

    # --- refinements ---------------------------------------------------------------------------------------
    def durably(self, write: Callable[[], object], what: str, cancel: threading.Event | None = None) -> bool:
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

    def publish_sweep(self, sweep_id: int) -> None:
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
