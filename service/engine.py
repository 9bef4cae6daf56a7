"""The run engine: one worker thread owns the bench and runs queued jobs one at a time.

State machines are tables (an Enum plus the transitions allowed); every state write goes through
`_set_job` / `_set_sweep`, which check the table; any other transition is a bug and raises. A sweep
runs its plan point by point; each point's result is committed in its own transaction before the
next point starts, and a failing point is stored as failed and the sweep goes on. Pause takes effect
between points, cancel between points or inside a measurement; the bench is left safe (torque off,
injection off) in every case.

Surviving the night: an interlock trip discards the point in flight (stored as a failed,
discarded attempt, never ok), pauses the sweep with the reason and measures that point again on
resume. A sweep the service stopped under (crash, kill -9, shutdown) is `interrupted` when the
service starts again; resume (or `engine.auto_resume`) measures only the points not yet committed,
and each point keeps one current result (earlier attempts are history: results.superseded_by).
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import traceback
from dataclasses import dataclass, field
from enum import Enum

from service.events import EventBroker
from service import __version__
from service.limits import check_limits
from service.interlocks import InterlockTripped
from service.identify import check_plant_time, identify_at, parse_options
from service.public import result_public, result_row
from service.maps import build_map_from_sweep
from service.map_validation import (ValidationOptions, ValidationStopped, check_points, check_validatable, run_validation,
                                    store_validation)
from service.neighbours import prior_from_neighbours
from service.operating_point import OperatingPoint
from service.plans import Grid, SweepPlan
from service.recordings import RecordingStore, RunRecorder
from service.settings import Settings
from service.storage import Storage, now_iso

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
    INTERRUPTED = "interrupted"     # the service stopped under it; resume measures what is missing
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


J, W = JobState, SweepState
JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    J.QUEUED: frozenset({J.RUNNING, J.CANCELLED, J.FAILED}),   # failed: the service stopped before it ran
    J.RUNNING: frozenset({J.DONE, J.FAILED, J.CANCELLED}),
    J.DONE: frozenset(), J.FAILED: frozenset(), J.CANCELLED: frozenset(),
}
SWEEP_TRANSITIONS: dict[SweepState, frozenset[SweepState]] = {
    W.QUEUED: frozenset({W.RUNNING, W.CANCELLED, W.PAUSED, W.INTERRUPTED}),
    W.RUNNING: frozenset({W.PAUSED, W.DONE, W.FAILED, W.CANCELLED, W.INTERRUPTED}),
    W.PAUSED: frozenset({W.RUNNING, W.CANCELLED, W.QUEUED, W.INTERRUPTED}),
    W.INTERRUPTED: frozenset({W.QUEUED, W.CANCELLED}),
    W.DONE: frozenset(), W.FAILED: frozenset(), W.CANCELLED: frozenset(),
}
UNFINISHED_SWEEP_STATES = frozenset({W.QUEUED, W.RUNNING, W.PAUSED})
del J, W


class TransitionError(RuntimeError):
    """A request that the current state does not allow (e.g. resume a finished sweep)."""


class Cancelled(Exception):
    pass


def check_transition(table, current, target) -> None:
    if target not in table[current]:
        raise TransitionError(f"cannot go from {current.value} to {target.value}")


@dataclass
class _SweepControl:
    pause: threading.Event = field(default_factory=threading.Event)
    cancel: threading.Event = field(default_factory=threading.Event)
    resumed: threading.Event = field(default_factory=threading.Event)


class Engine:
    def __init__(self, storage: Storage, bench, settings: Settings, broker: EventBroker,
                 recordings: RecordingStore | None = None):
        self.storage, self.bench, self.settings, self.broker = storage, bench, settings, broker
        self.recordings = recordings        # raw recording of every identification (None: none kept)
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._controls: dict[int, _SweepControl] = {}
        self._job_cancel: dict[int, threading.Event] = {}
        self._lock = threading.RLock()              # state read-check-write of jobs and sweeps
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
                    except TransitionError as exc:      # e.g. the drive faulted when we died: a person decides
                        log.warning("engine.auto_resume: sweep %s stays interrupted: %s", sweep["id"], exc)
                        self._set_sweep(sweep["id"], SweepState.INTERRUPTED,
                                        pause_reason=f"{sweep['pause_reason']}; not resumed automatically: {exc}")

    def recover(self) -> None:
        """On start-up: what a previous process left unfinished. Jobs cannot still be running (failed,
        with the reason); sweeps become `interrupted` (not failed), resumable."""
        for job in self.storage.unfinished_jobs():
            why = "the service stopped while this job was " + job["state"]
            if job["sweep_id"] is not None:
                why += f"; its sweep {job['sweep_id']} is interrupted: resume it"
            self._set_job(job["id"], JobState.FAILED, error=why, finished_at=now_iso())
        for sweep in self.storage.unfinished_sweeps():
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES:
                reason = (f"the service stopped while this sweep was {state.value} (no orderly shutdown: crash or "
                          f"kill); {sweep['done_points']} of {sweep['total_points']} points are stored, resume to "
                          "measure the rest")
                self._set_sweep(sweep["id"], SweepState.INTERRUPTED, pause_reason=reason)

    def stop(self, reason: str | None = None, timeout_s: float = 30.0) -> None:
        """Orderly shutdown: the run in flight stops (bench left safe), unfinished sweeps become
        `interrupted` with `reason` (e.g. "service shut down (SIGTERM)") in their pause_reason."""
        if reason:
            self._shutdown_reason = reason
        self._shutdown.set()
        for ctl in list(self._controls.values()):
            ctl.cancel.set()
            ctl.resumed.set()
        for ev in list(self._job_cancel.values()):
            ev.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)
        for sweep in self.storage.unfinished_sweeps():
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES:
                self._set_sweep(sweep["id"], SweepState.INTERRUPTED,
                                pause_reason=f"{self._shutdown_reason} while this sweep was {state.value}; "
                                             f"{sweep['done_points']} of {sweep['total_points']} points are stored")

    # --- state writes (every one through the tables) ----------------------------------------------------------
    def _set_job(self, job_id: int, target: JobState, **fields) -> None:
        """Check the transition, write it, tell the subscribers (SSE)."""
        with self._lock:
            current = JobState(self.storage.get_job(job_id)["state"])
            if current != target:
                check_transition(JOB_TRANSITIONS, current, target)
            self.storage.update_job(job_id, state=target.value, **fields)
        self._publish_job(job_id)

    def _set_sweep(self, sweep_id: int, target: SweepState, **fields) -> None:
        """Check the transition, write it, tell the subscribers (SSE). A same-state write only updates
        fields (e.g. a new pause_reason)."""
        with self._lock:
            current = SweepState(self.storage.get_sweep(sweep_id)["state"])
            if current != target:
                check_transition(SWEEP_TRANSITIONS, current, target)
            self.storage.update_sweep(sweep_id, state=target.value, **fields)
        self._publish_sweep(sweep_id)

    # --- submitting --------------------------------------------------------------------------------------
    def submit_identification(self, op: OperatingPoint, method: str, options) -> int:
        check_limits(op, self.settings)                     # refuse before anything is queued
        check_plant_time([op.speed_rpm], method, options, self.settings)
        job_id = self.storage.create_job("identification", {"operating_point": op.model_dump(), "method": method,
                                                             "options": options.model_dump()})
        self._job_cancel[job_id] = threading.Event()
        self._queue.put(job_id)
        self._publish_job(job_id)
        return job_id

    def submit_sweep(self, grid: Grid, method: str, options, schedule_id: int | None = None) -> int:
        plan = SweepPlan.from_grid(grid)
        check_plant_time(grid.speed_rpm, method, options, self.settings)
        plan.dry_run(self.settings)                         # every setpoint checked before the first frame
        sweep_id = self.storage.create_sweep(method, self.settings.identification.harmonic_order, grid.model_dump(),
                                             options.model_dump(), len(plan.points), self.bench.identity, __version__,
                                             schedule_id=schedule_id)
        self._queue_sweep(sweep_id)
        return sweep_id

    def submit_validation(self, map_id: int, force: bool, options: ValidationOptions) -> int:
        """Queue the validation of a map in the drive's LUT mode (service.map_validation). Refused before
        anything is queued: KeyError (no such map), ValidationRefused (no valid cell, partial without
        force), LimitError (a point outside the bench's limits)."""
        row = self.storage.get_map(map_id)
        if row is None:
            raise KeyError(map_id)
        check_validatable(self.storage, map_id, force)
        check_points(json.loads(row["axes_json"]), self.settings)
        job_id = self.storage.create_job("validation", {"map_id": map_id, "force": force,
                                                        "options": options.model_dump()})
        self._job_cancel[job_id] = threading.Event()
        self._queue.put(job_id)
        self._publish_job(job_id)
        return job_id

    def _queue_sweep(self, sweep_id: int) -> None:
        job_id = self.storage.create_job("sweep", {"sweep_id": sweep_id}, sweep_id=sweep_id)
        self._controls[sweep_id] = _SweepControl()
        self._job_cancel[job_id] = self._controls[sweep_id].cancel
        self._queue.put(job_id)
        self._publish_sweep(sweep_id)

    # --- controlling sweeps ---------------------------------------------------------------------------------
    def pause_sweep(self, sweep_id: int) -> None:
        with self._lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED)
            ctl = self._control(sweep_id)
            ctl.resumed.clear()
            ctl.pause.set()
            if state == SweepState.QUEUED:
                self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
        self._publish_sweep(sweep_id)

    def resume_sweep(self, sweep_id: int) -> None:
        """Resume a paused sweep, or one a previous service run left `interrupted` (it is queued again
        and measures only the points not yet committed). Refused while an interlock is tripped."""
        with self._lock:
            state = self._sweep_state(sweep_id)
            if state not in (SweepState.PAUSED, SweepState.INTERRUPTED):
                raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused or interrupted")
            trip = self.bench.interlock_refusal()
            if trip is not None:
                raise TransitionError(f"sweep {sweep_id} cannot resume: interlock tripped: {trip.reason}"
                                      + ("; acknowledge it with POST /api/v1/bench/fault-reset" if trip.latched else ""))
            if state == SweepState.INTERRUPTED:
                self._set_sweep(sweep_id, SweepState.QUEUED, pause_reason=None, finished_at=None)
                self._queue_sweep(sweep_id)
                return
            ctl = self._control(sweep_id)
            ctl.pause.clear()
            ctl.resumed.set()
            sweep = self.storage.get_sweep(sweep_id)
            self._set_sweep(sweep_id, SweepState.RUNNING if sweep["started_at"] else SweepState.QUEUED, pause_reason=None)
        self._publish_sweep(sweep_id)

    def cancel_sweep(self, sweep_id: int) -> None:
        with self._lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
            if state == SweepState.INTERRUPTED:
                self._set_sweep(sweep_id, SweepState.CANCELLED, finished_at=now_iso())
            else:
                ctl = self._control(sweep_id)
                ctl.cancel.set()
                ctl.resumed.set()
                if state in (SweepState.QUEUED, SweepState.PAUSED) and not self.storage.get_sweep(sweep_id)["started_at"]:
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
        if ctl is None:     # a paused/queued sweep always has one in this process (others are interrupted)
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
            self._set_job(job_id, JobState.FAILED, error=f"{self._shutdown_reason} before this job ran",
                          finished_at=now_iso())
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
            else:
                self._run_sweep(job_id, job["sweep_id"])
            final = JobState.CANCELLED if cancel.is_set() else JobState.DONE
            self._set_job(job_id, final, finished_at=now_iso(),
                          error=self._shutdown_reason if self._shutdown.is_set() else None)
        except Cancelled:
            self._set_job(job_id, JobState.CANCELLED, finished_at=now_iso(),
                          error=self._shutdown_reason if self._shutdown.is_set() else None)
        except Exception as exc:
            log.error("job %s failed: %s", job_id, traceback.format_exc())
            error = _error_text(exc)
            self._set_job(job_id, JobState.FAILED, error=error, finished_at=now_iso())
            sweep = self.storage.get_sweep(job["sweep_id"]) if job["sweep_id"] is not None else None
            if sweep is not None and SweepState(sweep["state"]) not in (SweepState.CANCELLED, SweepState.DONE,
                                                                         SweepState.FAILED):
                self._set_sweep(job["sweep_id"], SweepState.FAILED, error=error, finished_at=now_iso())
        self._publish_job(job_id)

    def _run_identification(self, job_id: int, job: dict) -> None:
        req = json.loads(job["request_json"])
        op = OperatingPoint.model_validate(req["operating_point"])
        options = parse_options(req["method"], req["options"])
        started = now_iso()
        recorder = self._new_recorder()
        try:
            result = identify_at(self.bench, self.settings, op, req["method"], options, cancel=self._job_cancel[job_id],
                                 progress=lambda w: self._publish_window(job_id, w), recorder=recorder)
        except Exception as exc:
            if self._job_cancel[job_id].is_set() and not isinstance(exc, InterlockTripped):
                _discard(recorder)
                raise Cancelled() from exc
            row = result_row(op, req["method"], options, self.bench.identity, started, error=_error_text(exc),
                             job_id=job_id, harmonic_order=self.settings.identification.harmonic_order)
            rid = self._insert_result(row, recorder)
            self.storage.update_job(job_id, result_id=rid)
            raise
        rid = self._insert_result(result_row(op, req["method"], options, self.bench.identity, started, result,
                                             job_id=job_id, harmonic_order=result.harmonic_order), recorder)
        self.storage.update_job(job_id, result_id=rid)

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
        req = json.loads(job["request_json"])
        options = ValidationOptions.model_validate(req["options"])

        def on_cell(cell: dict, total: int) -> None:
            self.broker.publish("job.progress", {"job_id": job_id, "kind": "validation", "total": total, "cell": cell})
        run = run_validation(self.storage, self.bench, self.settings, req["map_id"], req["force"], options,
                             self._job_cancel[job_id], on_cell=on_cell)
        store_validation(self.storage, job_id, run, self.bench.identity)
        if run.state == "cancelled":
            raise Cancelled()
        if run.state == "failed":
            raise ValidationStopped(run.error)

    def _run_sweep(self, job_id: int, sweep_id: int) -> None:
        sweep = self.storage.get_sweep(sweep_id)
        ctl = self._controls[sweep_id]
        grid = Grid.model_validate(json.loads(sweep["grid_json"]))
        options = parse_options(sweep["method"], json.loads(sweep["options_json"]))
        plan = SweepPlan.from_grid(grid)
        done = self.storage.committed_points(sweep_id)          # a resumed sweep measures only the rest
        if ctl.cancel.is_set() or SweepState(sweep["state"]) == SweepState.CANCELLED:
            raise Cancelled()       # cancelled as the worker took it: nothing was run
        self._set_sweep(sweep_id, SweepState.RUNNING, started_at=sweep["started_at"] or now_iso(), pause_reason=None)
        in_flight = None
        points = [op for op in plan.points if (op.torque_nm, op.speed_rpm, op.udc_v) not in done]
        i = 0
        while i < len(points):
            op = points[i]
            self._hold_while_paused(sweep_id, ctl)
            if ctl.cancel.is_set():
                break
            in_flight = op
            started = now_iso()
            recorder = self._new_recorder()
            try:
                prior = prior_from_neighbours(op, self.storage.sweep_results(sweep_id), grid.model_dump())
                result = identify_at(self.bench, self.settings, op, sweep["method"], options, prior=prior,
                                     cancel=ctl.cancel, recorder=recorder)
                row = result_row(op, sweep["method"], options, self.bench.identity, started, result,
                                 sweep_id=sweep_id, harmonic_order=result.harmonic_order)
            except InterlockTripped as exc:
                # the point is measured again after the operator resumes; its attempt (if any
                # torque was commanded) is kept as a failed, discarded attempt, never ok
                if not exc.refused:
                    self._store_point(sweep_id, op, self._discarded_row(op, sweep, options, started, exc, sweep_id),
                                      recorder)
                else:
                    _discard(recorder)
                self._pause_for_interlock(sweep_id, ctl, op, exc)
                continue
            except Exception as exc:
                if ctl.cancel.is_set():
                    _discard(recorder)
                    break
                log.warning("sweep %s point %s failed: %s", sweep_id, op.label(), exc)
                row = result_row(op, sweep["method"], options, self.bench.identity, started,
                                 error=_error_text(exc), sweep_id=sweep_id,
                                 harmonic_order=self.settings.identification.harmonic_order)
            self._store_point(sweep_id, op, row, recorder)
            in_flight = None
            i += 1
        if self._shutdown.is_set():
            s = self.storage.get_sweep(sweep_id)
            where = f" during point {in_flight.label()} (measured again on resume)" if in_flight is not None else ""
            self._set_sweep(sweep_id, SweepState.INTERRUPTED,
                            pause_reason=f"{self._shutdown_reason}{where}; {s['done_points']} of {s['total_points']} "
                                         "points are stored")
            return
        map_id = build_map_from_sweep(self.storage, sweep_id)
        final = SweepState.CANCELLED if ctl.cancel.is_set() else SweepState.DONE
        self._set_sweep(sweep_id, final, finished_at=now_iso(), map_id=map_id)

    def _store_point(self, sweep_id: int, op: OperatingPoint, row: dict, recorder: RunRecorder | None) -> None:
        rid = self._insert_result(row, recorder)
        self.broker.publish("sweep.point", {"sweep_id": sweep_id, "operating_point": op.model_dump(),
                                            "state": row["status"],
                                            "result": result_public(self.storage.get_result(rid), with_traces=False).model_dump()})
        self._publish_sweep(sweep_id)

    def _discarded_row(self, op, sweep, options, started, exc: InterlockTripped, sweep_id: int) -> dict:
        row = result_row(op, sweep["method"], options, self.bench.identity, started, error=_error_text(exc),
                         sweep_id=sweep_id, harmonic_order=self.settings.identification.harmonic_order)
        row["detail_json"] = json.dumps({"message": str(exc), "discarded": "interlock", "interlock": exc.trip.public()})
        return row

    def _pause_for_interlock(self, sweep_id: int, ctl: _SweepControl, op: OperatingPoint, exc: InterlockTripped) -> None:
        reason = (f"{exc.trip.reason} during point {op.label()}"
                  + (" (refused before it started)" if exc.refused else " (discarded; measured again on resume)")
                  + ("; acknowledge with POST /api/v1/bench/fault-reset, then resume" if exc.trip.latched else "; resume when it has cleared"))
        with self._lock:
            ctl.resumed.clear()
            ctl.pause.set()
            self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason=reason)
        log.warning("sweep %s paused: %s", sweep_id, reason)
        self._publish_sweep(sweep_id)

    def _hold_while_paused(self, sweep_id: int, ctl: _SweepControl) -> None:
        if not ctl.pause.is_set():
            return
        with self._lock:
            if SweepState(self.storage.get_sweep(sweep_id)["state"]) != SweepState.PAUSED:
                self._set_sweep(sweep_id, SweepState.PAUSED, pause_reason="paused by the operator")
        self._publish_sweep(sweep_id)
        while not ctl.resumed.wait(timeout=1.0):   # bounded waits; the bench is already safe between points
            if ctl.cancel.is_set():
                return
        if not ctl.cancel.is_set():
            with self._lock:
                self._set_sweep(sweep_id, SweepState.RUNNING, pause_reason=None)
            self._publish_sweep(sweep_id)

    # --- events ----------------------------------------------------------------------------------------------
    def _publish_job(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        self.broker.publish("job.state", {"job_id": job_id, "state": job["state"], "kind": job["kind"],
                                          "error": job["error"]})

    def _publish_window(self, job_id: int, window) -> None:
        """A run's accepted window as it comes (plant time on the DAQ clock, residual in full scale)."""
        self.broker.publish("job.progress", {"job_id": job_id, "plant_time_s": window.end_time_s,
                                             "residual_fs": window.phasor.amplitude,
                                             "noise_std_fs": window.noise_std_fs})

    def _publish_sweep(self, sweep_id: int) -> None:
        s = self.storage.get_sweep(sweep_id)
        self.broker.publish("sweep.progress", {"sweep_id": sweep_id, "state": s["state"], "done": s["done_points"],
                                               "total": s["total_points"], "map_id": s["map_id"],
                                               "pause_reason": s["pause_reason"]})


def _discard(recorder: RunRecorder | None) -> None:
    """A run that leaves no result (cancelled, refused) leaves no recording either."""
    if recorder is not None:
        recorder.close()


def _error_text(exc: BaseException) -> str:
    """'Type: message' plus any notes (e.g. what failed after an interlock trip)."""
    text = f"{type(exc).__name__}: {exc}"
    notes = getattr(exc, "__notes__", None)
    return text + "".join(f"; {n}" for n in notes) if notes else text
