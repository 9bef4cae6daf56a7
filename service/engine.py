"""The run engine: one worker thread owns the bench and runs queued jobs one at a time.

State machines are tables (an Enum plus the transitions allowed); any other transition is a bug
and raises. A sweep runs its plan point by point; each point's result is committed in its own
transaction before the next point starts, and a failing point is stored as failed and the sweep
goes on. Pause takes effect between points, cancel between points or inside a measurement; the
bench is left safe (torque off, injection off) in every case.
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
from service.bench import check_limits
from service.identify import identify_at, parse_options, public_result, result_row
from service.maps import build_map_from_sweep
from service.neighbours import prior_from_neighbours
from service.operating_point import OperatingPoint
from service.plans import Grid, SweepPlan
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
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


J, W = JobState, SweepState
JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    J.QUEUED: frozenset({J.RUNNING, J.CANCELLED}),
    J.RUNNING: frozenset({J.DONE, J.FAILED, J.CANCELLED}),
    J.DONE: frozenset(), J.FAILED: frozenset(), J.CANCELLED: frozenset(),
}
SWEEP_TRANSITIONS: dict[SweepState, frozenset[SweepState]] = {
    W.QUEUED: frozenset({W.RUNNING, W.CANCELLED, W.PAUSED}),
    W.RUNNING: frozenset({W.PAUSED, W.DONE, W.FAILED, W.CANCELLED}),
    W.PAUSED: frozenset({W.RUNNING, W.CANCELLED, W.QUEUED}),
    W.DONE: frozenset(), W.FAILED: frozenset(), W.CANCELLED: frozenset(),
}
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
    def __init__(self, storage: Storage, bench, settings: Settings, broker: EventBroker):
        self.storage, self.bench, self.settings, self.broker = storage, bench, settings, broker
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._controls: dict[int, _SweepControl] = {}
        self._job_cancel: dict[int, threading.Event] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # --- lifecycle -----------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._work, name="ripplecal-engine", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        for ctl in self._controls.values():
            ctl.cancel.set()
            ctl.resumed.set()
        for ev in self._job_cancel.values():
            ev.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)

    # --- submitting --------------------------------------------------------------------------------------
    def submit_identification(self, op: OperatingPoint, method: str, options) -> int:
        check_limits(op, self.settings)                     # refuse before anything is queued
        job_id = self.storage.create_job("identification", {"operating_point": op.model_dump(), "method": method,
                                                             "options": options.model_dump()})
        self._job_cancel[job_id] = threading.Event()
        self._queue.put(job_id)
        self._publish_job(job_id)
        return job_id

    def submit_sweep(self, grid: Grid, method: str, options) -> int:
        plan = SweepPlan.from_grid(grid)
        plan.dry_run(self.settings)                         # every setpoint checked before the first frame
        sweep_id = self.storage.create_sweep(method, self.settings.identification.harmonic_order, grid.model_dump(),
                                             options.model_dump(), len(plan.points), self.bench.identity, __version__)
        job_id = self.storage.create_job("sweep", {"sweep_id": sweep_id}, sweep_id=sweep_id)
        self._controls[sweep_id] = _SweepControl()
        self._job_cancel[job_id] = self._controls[sweep_id].cancel
        self._queue.put(job_id)
        self._publish_sweep(sweep_id)
        return sweep_id

    # --- controlling sweeps ---------------------------------------------------------------------------------
    def pause_sweep(self, sweep_id: int) -> None:
        with self._lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED)
            ctl = self._controls[sweep_id]
            ctl.resumed.clear()
            ctl.pause.set()
            if state == SweepState.QUEUED:
                self.storage.update_sweep(sweep_id, state="paused")
        self._publish_sweep(sweep_id)

    def resume_sweep(self, sweep_id: int) -> None:
        with self._lock:
            state = self._sweep_state(sweep_id)
            if state != SweepState.PAUSED:
                raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused")
            ctl = self._controls[sweep_id]
            ctl.pause.clear()
            ctl.resumed.set()
            sweep = self.storage.get_sweep(sweep_id)
            self.storage.update_sweep(sweep_id, state="running" if sweep["started_at"] else "queued")
        self._publish_sweep(sweep_id)

    def cancel_sweep(self, sweep_id: int) -> None:
        with self._lock:
            state = self._sweep_state(sweep_id)
            check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
            ctl = self._controls[sweep_id]
            ctl.cancel.set()
            ctl.resumed.set()
            if state in (SweepState.QUEUED, SweepState.PAUSED) and not self.storage.get_sweep(sweep_id)["started_at"]:
                self.storage.update_sweep(sweep_id, state="cancelled", finished_at=now_iso())
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
            self.storage.update_job(job_id, state="cancelled", finished_at=now_iso())
            self._publish_job(job_id)

    def _sweep_state(self, sweep_id: int) -> SweepState:
        sweep = self.storage.get_sweep(sweep_id)
        if sweep is None or sweep_id not in self._controls:
            raise KeyError(sweep_id)
        return SweepState(sweep["state"])

    # --- the worker ------------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job_id = self._queue.get()
            if job_id is None:
                return
            job = self.storage.get_job(job_id)
            if job is None or job["state"] != "queued":
                continue
            cancel = self._job_cancel.setdefault(job_id, threading.Event())
            if cancel.is_set():
                self.storage.update_job(job_id, state="cancelled", finished_at=now_iso())
                continue
            self.storage.update_job(job_id, state="running", started_at=now_iso())
            self._publish_job(job_id)
            try:
                if job["kind"] == "identification":
                    self._run_identification(job_id, job)
                else:
                    self._run_sweep(job_id, job["sweep_id"])
                final = "cancelled" if cancel.is_set() else "done"
                self.storage.update_job(job_id, state=final, finished_at=now_iso())
            except Cancelled:
                self.storage.update_job(job_id, state="cancelled", finished_at=now_iso())
            except Exception as exc:
                log.error("job %s failed: %s", job_id, traceback.format_exc())
                error = f"{type(exc).__name__}: {exc}"
                self.storage.update_job(job_id, state="failed", error=error, finished_at=now_iso())
                if job["sweep_id"] is not None:
                    self.storage.update_sweep(job["sweep_id"], state="failed", error=error, finished_at=now_iso())
                    self._publish_sweep(job["sweep_id"])
            self._publish_job(job_id)

    def _run_identification(self, job_id: int, job: dict) -> None:
        req = json.loads(job["request_json"])
        op = OperatingPoint.model_validate(req["operating_point"])
        options = parse_options(req["method"], req["options"])
        started = now_iso()
        self.bench.cancel_event = self._job_cancel[job_id]
        try:
            result = identify_at(self.bench, self.settings, op, req["method"], options)
        except Exception as exc:
            if self._job_cancel[job_id].is_set():
                raise Cancelled() from exc
            row = result_row(op, req["method"], options, self.bench.identity, started, error=f"{type(exc).__name__}: {exc}",
                             job_id=job_id, harmonic_order=self.settings.identification.harmonic_order)
            rid = self.storage.insert_result(row)
            self.storage.update_job(job_id, result_id=rid)
            raise
        finally:
            self.bench.cancel_event = None
        rid = self.storage.insert_result(result_row(op, req["method"], options, self.bench.identity, started, result,
                                                    job_id=job_id, harmonic_order=result.harmonic_order))
        self.storage.update_job(job_id, result_id=rid)

    def _run_sweep(self, job_id: int, sweep_id: int) -> None:
        sweep = self.storage.get_sweep(sweep_id)
        ctl = self._controls[sweep_id]
        grid = Grid.model_validate(json.loads(sweep["grid_json"]))
        options = parse_options(sweep["method"], json.loads(sweep["options_json"]))
        plan = SweepPlan.from_grid(grid)
        done = {(r["torque_nm"], r["speed_rpm"], r["udc_v"]) for r in self.storage.sweep_results(sweep_id)}
        self.storage.update_sweep(sweep_id, state="running", started_at=sweep["started_at"] or now_iso())
        self._publish_sweep(sweep_id)
        self.bench.cancel_event = ctl.cancel
        try:
            for op in plan.points:
                if (op.torque_nm, op.speed_rpm, op.udc_v) in done:
                    continue
                self._hold_while_paused(sweep_id, ctl)
                if ctl.cancel.is_set():
                    break
                started = now_iso()
                try:
                    prior = prior_from_neighbours(op, self.storage.sweep_results(sweep_id), grid.model_dump())
                    result = identify_at(self.bench, self.settings, op, sweep["method"], options, prior=prior)
                    row = result_row(op, sweep["method"], options, self.bench.identity, started, result,
                                     sweep_id=sweep_id, harmonic_order=result.harmonic_order)
                except Exception as exc:
                    if ctl.cancel.is_set():
                        break
                    log.warning("sweep %s point %s failed: %s", sweep_id, op.label(), exc)
                    row = result_row(op, sweep["method"], options, self.bench.identity, started,
                                     error=f"{type(exc).__name__}: {exc}", sweep_id=sweep_id,
                                     harmonic_order=self.settings.identification.harmonic_order)
                progress = {"done_points": 1, "failed_points": 0 if row["status"] != "failed" else 1}
                rid = self.storage.insert_result(row, sweep_progress=progress)
                self.broker.publish("sweep.point", {"sweep_id": sweep_id, "operating_point": op.model_dump(),
                                                    "state": row["status"],
                                                    "result": public_result({**self.storage.get_result(rid), "traces_json": "{}"})})
                self._publish_sweep(sweep_id)
        finally:
            self.bench.cancel_event = None
        map_id = build_map_from_sweep(self.storage, sweep_id)
        final = "cancelled" if ctl.cancel.is_set() else "done"
        self.storage.update_sweep(sweep_id, state=final, finished_at=now_iso(), map_id=map_id)
        self._publish_sweep(sweep_id)

    def _hold_while_paused(self, sweep_id: int, ctl: _SweepControl) -> None:
        if not ctl.pause.is_set():
            return
        self.storage.update_sweep(sweep_id, state="paused")
        self._publish_sweep(sweep_id)
        while not ctl.resumed.wait(timeout=1.0):   # bounded waits; the bench is already safe between points
            if ctl.cancel.is_set():
                return
        if not ctl.cancel.is_set():
            self.storage.update_sweep(sweep_id, state="running")
            self._publish_sweep(sweep_id)

    # --- events ----------------------------------------------------------------------------------------------
    def _publish_job(self, job_id: int) -> None:
        job = self.storage.get_job(job_id)
        self.broker.publish("job.state", {"job_id": job_id, "state": job["state"], "kind": job["kind"]})

    def _publish_sweep(self, sweep_id: int) -> None:
        s = self.storage.get_sweep(sweep_id)
        self.broker.publish("sweep.progress", {"sweep_id": sweep_id, "state": s["state"], "done": s["done_points"],
                                               "total": s["total_points"], "map_id": s["map_id"]})
