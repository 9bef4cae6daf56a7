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

import collections
import contextlib
import logging
import threading
import traceback
from typing import Callable, Iterator

from drivers.errors import DriverError
from service import __version__
from service.bench.bench import BenchError
from service.bench.interlocks import InterlockTripped
from service.bench.setpoint_accounting import AccountingError
from service.identification.session import MeasurementError
from service.maps.build import build_map_from_sweep
from service.maps.view import map_view
from service.model.limits import LimitError, check_point
from service.model.operating_point import OperatingPoint
from service.runs.events import EventBroker
from service.runs.identify import check_plant_time, identify_at, parse_options
from service.runs.lab import is_own_bench, job_event, new_instance_id, sweep_event
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
from service.store.records import SweepRecord
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
SWEEP_ACTIONS = ("pause", "resume", "cancel")  # what an operator may ask of a sweep (control_sweep)
CLAIM_POLL_S = 0.5  # the worker looks for its bench's jobs this often (and at once when this process queues one)


class Engine:
    def __init__(
        self,
        storage: Storage,
        bench,
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
        self._running_job: tuple[int, int | None] | None = None  # (job id, sweep id) the worker runs now
        self._controls: dict[int, SweepControl] = {}
        self._job_cancel: dict[int, threading.Event] = {}
        self._storage_waits: dict[int, str] = {}  # sweep id -> why it waits for the database (in memory only)
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
            for sweep in self.storage.bench_unfinished_sweeps(self.bench_name):
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
        jobs = self.storage.bench_unfinished_jobs(self.bench_name)
        kept = self._waiting_sweeps(jobs)
        for v in self.storage.bench_running_validations(self.bench_name):
            download = v["download"] or {}
            cells = v["cells"] or []
            lut = (
                f"the drive holds the LUT of map {download.get('map_id')} (CRC-32 {download.get('crc32')}) since this "
                "validation downloaded it"
            )
            error = f"the service stopped during this validation: {len(cells)} point(s) measured and kept; {lut}"
            self.storage.update_validation(v["id"], state="failed", error=error, finished_at=now_iso())
            held[v["job_id"]] = lut
        for job in jobs:
            if self._waits_for_bench(job, kept):
                continue  # queued for this bench while no service ran it: it runs now
            why = "the service stopped while this job was " + job["state"]
            if job["sweep_id"] is not None:
                why += f"; its sweep {job['sweep_id']} is interrupted: resume it"
            if job["id"] in held:
                why += f"; {held[job['id']]}"
            self.set_job(job["id"], JobState.FAILED, error=why, finished_at=now_iso())
        for sweep in self.storage.bench_unfinished_sweeps(self.bench_name):
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES and sweep["id"] not in kept:
                reason = (
                    f"the service stopped while this sweep was {state.value} (no orderly shutdown: crash or "
                    f"kill); {sweep['done_points']} of {sweep['total_points']} points are stored, resume to "
                    "measure the rest"
                )
                self.set_sweep(sweep["id"], SweepState.INTERRUPTED, pause_reason=reason)
        self.storage.adopt_unnamed_rows(self.bench_name)

    def _waiting_sweeps(self, jobs: list[dict]) -> set[int]:
        """Sweeps of this bench queued by another bench's service and not yet taken: they wait, untouched."""
        return {
            j["sweep_id"]
            for j in jobs
            if j["sweep_id"] is not None and j["state"] == "queued" and j["claimed_by"] is None and j["bench"]
        }

    def _waits_for_bench(self, job: dict, kept: set[int]) -> bool:
        """A job of this bench that no service has taken yet (queued elsewhere for it): not recovered."""
        if job["state"] != "queued" or job["claimed_by"] is not None or job["bench"] is None:
            return False
        return job["sweep_id"] is None or job["sweep_id"] in kept

    def stop(self, reason: str | None = None, timeout_s: float = 30.0) -> None:
        """Orderly shutdown: the run in flight stops (bench left safe), unfinished sweeps become
        `interrupted` with `reason` (e.g. "service shut down (SIGTERM)") in their pause_reason."""
        if reason:
            self._shutdown_reason = reason
        if self._running_job is not None:
            # the bench first, at once: the worker may be stuck (on the database) inside its run
            self.bench.stop_now(self._shutdown_reason)
        self._shutdown.set()
        for ctl in list(self._controls.values()):
            ctl.cancel.set()
        for ev in list(self._job_cancel.values()):
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
            self._mark_unfinished()
        except StorageUnavailable as exc:
            log.warning("shutdown: unfinished jobs and sweeps not marked (%s): the next start does it", exc)

    def _mark_unfinished(self) -> None:
        """At shutdown: jobs this process queued and did not run fail, unfinished sweeps are interrupted."""
        jobs = self.storage.bench_unfinished_jobs(self.bench_name)
        kept = self._waiting_sweeps(jobs)
        for job in jobs:  # what this process queued and did not run (a job queued elsewhere for the bench waits)
            if job["state"] == "queued" and job["claimed_by"] == self.instance:
                self.set_job(
                    job["id"],
                    JobState.FAILED,
                    error=f"{self._shutdown_reason} before this job ran",
                    finished_at=now_iso(),
                )
        for sweep in self.storage.bench_unfinished_sweeps(self.bench_name):
            state = SweepState(sweep["state"])
            if state in UNFINISHED_SWEEP_STATES and sweep["id"] not in kept:
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
    def submit_identification(self, op: OperatingPoint, method: str, options, bench: str | None = None) -> int:
        """`bench`: the bench it is for (default this one). Another bench's job is stored, and checked
        against that bench's settings by its own service when it takes it."""
        own = self.is_own(bench)
        if own:
            self.bench.check_reachable()  # refused now, not failed later
            check_point(op, self.settings, options.override_envelope_model)  # refuse before anything is queued
            check_plant_time([op.speed_rpm], method, options, self.settings)
        job_id = self._create_job(
            "identification",
            {"operating_point": op.model_dump(), "method": method, "options": options.model_dump()},
            bench=bench,
        )
        self._publish_job(job_id)
        return job_id

    def is_own(self, bench: str | None) -> bool:
        return is_own_bench(bench, self.bench_name)

    def _create_job(self, kind: str, request: dict, bench: str | None, sweep_id: int | None = None) -> int:
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
                self._job_cancel[job_id] = threading.Event()
            self._wake_for(job_id)
        return job_id

    def _wake_for(self, job_id: int) -> None:
        """A job of this bench was queued (or queued again) here: the worker claims it now."""
        self._mine.append(job_id)
        self._wake.set()

    def submit_sweep(
        self, grid: Grid, method: str, options, schedule_id: int | None = None, regime=None, bench: str | None = None
    ) -> int:
        """Queue a sweep over the planned grid: `grid` with the speeds `regime` (service.runs.plans.RegimePlacement)
        places around the predicted field-weakening onset (service.runs.plans.plan_grid, the grid POST
        /sweeps/preview shows). The planned grid is what the sweep stores, so its run and its map use the
        real axes. For another bench (`bench`) the grid is stored as given (its own service places and
        checks it against its settings when it takes the sweep; a regime placement needs that bench's
        machine: refused here)."""
        own = self.is_own(bench)
        if own:
            self.bench.check_reachable()
            grid = plan_grid(grid, regime, self.settings).grid
        elif regime is not None:
            raise ValueError(f"regime placement needs bench {bench}'s machine settings: post it to its service")
        plan = SweepPlan.from_grid(grid)
        if own:
            check_plant_time(grid.speed_rpm, method, options, self.settings)
            # every setpoint checked before the first frame
            plan.dry_run(self.settings, options.override_envelope_model)
        sweep_id = self.storage.create_sweep(
            method,
            self.settings.identification.harmonic_order,
            grid.model_dump(),
            options.model_dump(),
            len(plan.points),
            self.bench.identity if own else f"bench {bench}",  # its service writes the identity when it starts it
            __version__,
            schedule_id=schedule_id,
            bench=self.bench_name if own else bench,
        )
        self._queue_sweep(sweep_id)
        return sweep_id

    def submit_validation(self, map_id: int, force: bool, options: ValidationOptions, bench: str | None = None) -> int:
        """Queue the validation of a map in the drive's LUT mode (service.runs.validation). Refused before
        anything is queued: KeyError (no such map), ValidationRefused (no valid cell, partial without
        force), LimitError (a point outside the bench's limits; another bench's service checks its own)."""
        own = self.is_own(bench)
        if own:
            self.bench.check_reachable()
        row = self.storage.get_map(map_id)
        if row is None:
            raise KeyError(map_id)
        check_validatable(self.storage, map_id, force, fill=options.fill)
        if own:
            check_points(row["axes"], self.settings, options.override_envelope_model)
        job_id = self._create_job(
            "validation", {"map_id": map_id, "force": force, "options": options.model_dump()}, bench=bench
        )
        self._publish_job(job_id)
        return job_id

    def submit_refinement(self, map_id: int, request: RefineRequest, bench: str | None = None) -> int:
        """Queue the refinement of a map (service/runs/refinement.py) as a sweep of kind `refinement`: its
        cells, pause, resume, cancel and crash-resume are a sweep's. Refused before anything is
        queued: KeyError (no such map), ValueError (method or options), LimitError (a validation point
        outside the bench's limits). A partial map is accepted: its non-ok cells are measured first.
        Returns the job's id."""
        own = self.is_own(bench)
        if own:
            self.bench.check_reachable()
        m = map_view(self.storage, map_id)
        if m is None:
            raise KeyError(map_id)
        check_request(request)
        options = parse_options(request.method, request.options)
        if own:
            # a refinement measures cells (its method options) and validates (its validation options)
            check_points(
                m.axes,
                self.settings,
                options.override_envelope_model and request.validation.override_envelope_model,
            )
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
            self.bench.identity if own else f"bench {bench}",
            __version__,
            kind="refinement",
            source_map_id=map_id,
            refinement=state,
            bench=self.bench_name if own else bench,
        )
        return self._queue_sweep(sweep_id)

    def _queue_sweep(self, sweep_id: int) -> int:
        sweep = self.storage.get_sweep(sweep_id)
        kind = sweep.get("kind") or "sweep"  # a refinement runs as a sweep of its kind
        if self.is_own(sweep.get("bench")):
            self._controls[sweep_id] = SweepControl()
        job_id = self._create_job(kind, {"sweep_id": sweep_id}, bench=sweep.get("bench"), sweep_id=sweep_id)
        if sweep_id in self._controls:
            self._job_cancel[job_id] = self._controls[sweep_id].cancel
        self.publish_sweep(sweep_id)
        return job_id

    # --- controlling sweeps ---------------------------------------------------------------------------------
    def control_sweep(self, sweep_id: int, action: str) -> None:
        """`action`: pause | resume | cancel. Another bench's sweep: checked against the table here, then
        asked of its bench's service through the database (sweeps.control_request), which acts on it within
        about a second (act_on_control_requests); a queued one no service has taken is cancelled here.
        A cancel of the sweep this process runs acts on the bench first, before the database is asked."""
        if action == "cancel":
            self._cancel_running(sweep_id=sweep_id)
            known = self.storage.known_unavailable()
            if known is not None:  # the run (if any) is stopped: the rest waits for the database (503 at once)
                raise StorageUnavailable(known.cause, str(known), known.retry_after_s, known.public)
        try:
            sweep = self.storage.get_sweep(sweep_id)
        except StorageUnavailable:
            if action == "cancel":
                raise  # its run is stopped and its bench safe already (503: the rest when the database answers)
            return self._act(sweep_id, action)
        if sweep is None:
            raise KeyError(sweep_id)
        if self.is_own(sweep.get("bench")):
            return self._act(sweep_id, action)
        state = SweepState(sweep["state"])
        if action == "cancel" and state == SweepState.QUEUED:
            check_transition(SWEEP_TRANSITIONS, state, SweepState.CANCELLED)
            check_transition(JOB_TRANSITIONS, JobState.QUEUED, JobState.CANCELLED)
            if self.storage.cancel_waiting_sweep(sweep_id):
                return self.publish_sweep(sweep_id)
        if action == "resume":
            if state not in (SweepState.PAUSED, SweepState.INTERRUPTED):
                raise TransitionError(f"sweep {sweep_id} is {state.value}, not paused or interrupted")
        else:
            check_transition(SWEEP_TRANSITIONS, state, SweepState.PAUSED if action == "pause" else SweepState.CANCELLED)
        self.storage.request_sweep_control(sweep_id, action)
        self.publish_sweep(sweep_id)

    def act_on_control_requests(self) -> None:
        """Pause, resume or cancel asked at another bench's service for this bench's sweeps (the lab thread
        calls this every second). A refusal is noted on the sweep (control_note) for whoever asked."""
        for sweep_id, action in self.storage.sweep_control_requests(self.bench_name):
            if action not in SWEEP_ACTIONS or not self.storage.take_sweep_control(sweep_id, action):
                continue
            try:
                self._act(sweep_id, action)
            except (TransitionError, KeyError) as exc:
                note = f"{action} asked at another bench's service: refused by bench {self.bench_name}: {exc}"
                log.warning("sweep %s: %s", sweep_id, note)
                self.storage.update_sweep(sweep_id, control_note=note)
                self.publish_sweep(sweep_id)

    def _act(self, sweep_id: int, action: str) -> None:
        """One of SWEEP_ACTIONS on a sweep this process runs."""
        {"pause": self.pause_sweep, "resume": self.resume_sweep, "cancel": self.cancel_sweep}[action](sweep_id)

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
                self._wake_for(job_id)
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

    def _cancel_running(self, job_id: int | None = None, sweep_id: int | None = None) -> None:
        """A cancel of what the worker runs now: its token set and the bench made safe at once (the
        watchdog's thread), whatever the worker is doing; no database, no lock. Anything else: nothing."""
        running = self._running_job
        if running is None or not (
            (job_id is not None and running[0] == job_id) or (sweep_id is not None and running[1] == sweep_id)
        ):
            return
        if running[1] is not None:
            self._control(running[1]).cancel.set()
        if running[0] in self._job_cancel:
            self._job_cancel[running[0]].set()
        what = f"sweep {running[1]}" if running[1] is not None else f"job {running[0]}"
        self.bench.stop_now(f"{what} cancelled")

    def cancel_job(self, job_id: int) -> None:
        self._cancel_running(job_id=job_id)
        known = self.storage.known_unavailable()
        if known is not None:  # the run (if any) is stopped: the rest waits for the database (503 at once)
            raise StorageUnavailable(known.cause, str(known), known.retry_after_s, known.public)
        job = self.storage.get_job(job_id)
        if job is None:
            raise KeyError(job_id)
        check_transition(JOB_TRANSITIONS, JobState(job["state"]), JobState.CANCELLED)
        if job["sweep_id"] is not None:
            return self.cancel_sweep(job["sweep_id"])
        if not self.is_own(job.get("bench")):
            if job["state"] != "queued":  # its run is in the other service's hands
                raise TransitionError(f"job {job_id} runs on bench {job['bench']}: ask the service of that bench")
            # queued: no service has taken it; a conditional write, so a claim at this moment wins cleanly
            if not self.storage.cancel_queued_job(job_id):
                raise TransitionError(f"job {job_id} was taken by bench {job['bench']} just now: ask its service")
            return self._publish_job(job_id)
        self._job_cancel.setdefault(job_id, threading.Event()).set()
        if job["state"] == "queued":
            self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())

    def _sweep_state(self, sweep_id: int) -> SweepState:
        sweep = self.storage.get_sweep(sweep_id)
        if sweep is None:
            raise KeyError(sweep_id)
        if not self.is_own(sweep.get("bench")):
            # only the bench's own service can stop its run between points
            raise TransitionError(
                f"sweep {sweep_id} is for bench {sweep['bench']}: ask the service of bench {sweep['bench']} "
                "(GET /api/v1/benches names its host and port)"
            )
        return SweepState(sweep["state"])

    def _control(self, sweep_id: int) -> SweepControl:
        # a sweep of this bench queued by another bench's service gets its controls here, as it gets them
        # when the worker takes it
        return self._controls.setdefault(sweep_id, SweepControl())

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
                self._running_job = None

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
            self._job_cancel[job_id] = self._control(job["sweep_id"]).cancel
        self.running = f"sweep {job['sweep_id']}" if job["sweep_id"] is not None else f"job {job_id}"
        self._running_job = (job_id, job["sweep_id"])
        cancel = self._job_cancel.setdefault(job_id, threading.Event())
        if self._shutdown.is_set():
            self.set_job(
                job_id, JobState.FAILED, error=f"{self._shutdown_reason} before this job ran", finished_at=now_iso()
            )
            return
        if cancel.is_set():
            self.set_job(job_id, JobState.CANCELLED, finished_at=now_iso())
            return
        self._publish_job(job_id)  # the claim wrote running and started_at (Storage.claim_job)
        try:
            self._check_here(job)
            if job["kind"] == "identification":
                self._run_identification(job_id, job)
            elif job["kind"] == "validation":
                self._run_validation(job_id, job)
            elif job["kind"] == "refinement":
                self._sweeps.run_refinement(job_id, job["sweep_id"], self._control(job["sweep_id"]))
            else:
                self._sweeps.run_sweep(job_id, job["sweep_id"], self._control(job["sweep_id"]))
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

    def _check_here(self, job: dict) -> None:
        """A job queued by another bench's service was checked only from its request: this bench's limits
        and plant time are checked now, and refuse it with the reason (the job fails, and its sweep). A job
        queued here passed the same checks at submit: checked again, as cheap as it is deterministic."""
        req = job["request"]
        if job["kind"] == "identification":
            op = OperatingPoint.model_validate(req["operating_point"])
            options = parse_options(req["method"], req["options"])
            check_point(op, self.settings, options.override_envelope_model)
            check_plant_time([op.speed_rpm], req["method"], options, self.settings)
        elif job["kind"] == "validation":
            override = bool(req["options"].get("override_envelope_model", False))
            check_points(self.storage.get_map(req["map_id"])["axes"], self.settings, override)
        elif job["sweep_id"] is not None:
            sweep = self.storage.get_sweep(job["sweep_id"])
            if sweep["started_at"] is None and sweep["bench_identity"] != self.bench.identity:
                override = bool(sweep["options"].get("override_envelope_model", False))
                if job["kind"] == "sweep":
                    SweepPlan.from_grid(Grid.model_validate(sweep["grid"])).dry_run(self.settings, override)
                else:
                    validation = (sweep.get("refinement") or {}).get("validation") or {}
                    override = override and bool(validation.get("override_envelope_model", False))
                    check_points(sweep["grid"], self.settings, override)
                self.storage.update_sweep(job["sweep_id"], bench_identity=self.bench.identity)

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
                self._wake_for(job_id)
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
        self.broker.publish("job.state", job_event(job))

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
        self.broker.publish("sweep.progress", sweep_event(self.as_seen(s)))

    # --- a sweep waiting for the database ------------------------------------------------------------------
    @contextlib.contextmanager
    def waiting_for_storage(self, sweep_id: int, reason: str) -> Iterator[None]:
        """While the sweep's run waits for the database (the bench safe). The database cannot take the
        pause, so it is held here: a database that can still be read (a full disk reads) shows it."""
        self._storage_waits[sweep_id] = reason
        try:
            yield
        finally:
            self._storage_waits.pop(sweep_id, None)

    def as_seen(self, sweep: SweepRecord) -> SweepRecord:
        """The sweep as stored, or paused with its reason while its run waits for the database."""
        reason = self._storage_waits.get(sweep["id"])
        if reason is None:
            return sweep
        return {**sweep, "state": SweepState.PAUSED.value, "pause_reason": reason}
