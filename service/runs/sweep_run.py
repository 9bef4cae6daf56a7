"""A sweep's run body: the points measured in continuous bench runs, the second pass, the map. The
engine (service/runs/engine.py) owns the queue, the worker and the state tables; the kind `sweep`
(service/runs/kinds/sweep.py) hands its job to `SweepRunner.run_sweep` with the sweep's controls, the
kind `refinement` measures its rounds' cells through `measure_points`, and the runner calls back only
through `RunHost`.

Each point's result is committed in its own transaction before the next point starts; a failing
point is stored as failed and the sweep goes on. An interlock trip discards the point in flight
(stored as a failed, discarded attempt, never ok) and pauses the sweep with the reason; the database
away keeps the point measured and writes it when it answers again.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, ContextManager, Protocol, cast

from service.bench.bench import Bench
from service.bench.trips import InterlockTripped
from service.errors import NotFound
from service.identification.common import LUT_MARGIN_DB, MethodOptions
from service.identification.session import MeasurementError
from service.maps.build import build_map_from_sweep
from service.maps.neighbours import prior_from_neighbours
from service.model.limits import LimitError, outside_envelope
from service.model.operating_point import OperatingPoint
from service.runs.events import EventBroker
from service.runs.identify import identify_in_run, parse_options, run_settings
from service.runs.plans import Grid, SweepPlan
from service.runs.states import Cancelled, Paused, SweepControl, SweepState
from service.settings import Settings
from service.store.recordings import RunRecorder
from service.store.records import JobRecord, ResultRecord, SweepRecord
from service.store.result_rows import result_row
from service.store.storage import Storage, StorageUnavailable, now_iso

log = logging.getLogger(__name__)


class RunHost(Protocol):
    """What a sweep's run body needs from the engine that runs it."""

    storage: Storage
    bench: Bench
    settings: Settings
    broker: EventBroker

    @property
    def lock(self) -> threading.RLock: ...
    @property
    def shutdown_reason(self) -> str: ...
    def shutting_down(self) -> bool: ...
    def set_sweep(self, sweep_id: int, target: SweepState, **fields: Any) -> None: ...
    def durably(self, write: Callable[[], object], what: str, cancel: threading.Event | None = None) -> bool: ...
    def publish_sweep(self, sweep_id: int) -> None: ...
    def insert_result(self, row: dict[str, Any], recorder: RunRecorder | None) -> int: ...
    def new_recorder(self) -> RunRecorder | None: ...
    def waiting_for_storage(self, sweep_id: int, reason: str) -> ContextManager[None]: ...


class SweepRunner:
    def __init__(self, host: RunHost):
        self.host = host
        self.storage, self.bench, self.settings, self.broker = host.storage, host.bench, host.settings, host.broker

    def run_sweep(self, job_id: int, sweep_id: int, ctl: SweepControl) -> None:
        """The sweep as continuous bench runs (service/bench/run.py): the drive stays enabled and the
        load turning from point to point; a run ends (bench made safe) on pause, cancel, an interlock
        trip, a failure of the bench itself, and at the end. A point that cannot be measured is stored
        failed and the run goes on; an interlock trip discards the point in flight and pauses.
        Two passes: every point, then once more each point whose result is not ok, with what its
        neighbours now know on every side (service/maps/neighbours.py); a cell that stays non-ok gets the fill
        rule's entry in the map (service/maps/fill.py)."""
        sweep = stored_sweep(self.storage, sweep_id)
        grid = Grid.model_validate(sweep["grid"])  # the planned grid, stored at submit
        options = parse_options(sweep["method"], sweep["options"])
        plan = stored_plan(sweep)
        done = self.storage.committed_points(sweep_id)  # a resumed sweep measures only the rest
        if ctl.cancel.is_set() or SweepState(sweep["state"]) == SweepState.CANCELLED:
            raise Cancelled()  # cancelled as the worker took it: nothing was run
        if ctl.pause.is_set():
            raise Paused()  # paused while it waited in the queue
        self.host.set_sweep(
            sweep_id, SweepState.RUNNING, started_at=sweep["started_at"] or now_iso(), pause_reason=None
        )
        first = [op for op in plan.points if (op.torque_nm, op.speed_rpm, op.udc_v) not in done]
        in_flight = self.measure_points(sweep_id, sweep, ctl, grid, options, first, sweep_pass=1)
        if in_flight is None and not ctl.cancel.is_set() and not self.host.shutting_down():
            again = [
                op
                for op in second_pass_points(plan, self.storage.sweep_results(sweep_id))
                if outside_envelope(op, self.settings, options.override_envelope_model) is None
            ]
            if again:
                log.info(
                    "sweep %s: %d point(s) not ok measured once more with their neighbours' priors",
                    sweep_id,
                    len(again),
                )
                in_flight = self.measure_points(sweep_id, sweep, ctl, grid, options, again, sweep_pass=2)
        if self.host.shutting_down():
            s = stored_sweep(self.storage, sweep_id)
            where = f" during point {in_flight.label()} (measured again on resume)" if in_flight is not None else ""
            self.host.set_sweep(
                sweep_id,
                SweepState.INTERRUPTED,
                pause_reason=f"{self.host.shutdown_reason}{where}; {s['done_points']} of {s['total_points']} "
                "points are stored",
            )
            return
        map_id = build_map_from_sweep(self.storage, sweep_id, cancelled=ctl.cancel.is_set())
        final = SweepState.CANCELLED if ctl.cancel.is_set() else SweepState.DONE
        self.host.set_sweep(sweep_id, final, finished_at=now_iso(), map_id=map_id)

    def measure_points(
        self,
        sweep_id: int,
        sweep: SweepRecord,
        ctl: SweepControl,
        grid: Grid,
        options: MethodOptions,
        points: list[OperatingPoint],
        sweep_pass: int,
        neighbour_rows: Callable[[], list[ResultRecord]] | None = None,
        tags: dict[str, Any] | None = None,
    ) -> OperatingPoint | None:
        """Measure `points` in continuous runs (see run_sweep), holding while paused. Returns the point
        in flight when a cancel or a shutdown stopped it (None when every point was measured or the
        stop came between points). Priors come from `neighbour_rows()` (default: the sweep's current
        results); `tags` go into every result's details."""
        rows_for_priors = neighbour_rows or (lambda: self.storage.sweep_results(sweep_id))
        tags = {"sweep_pass": sweep_pass, **(tags or {})}
        if options.stop_margin_db is None:  # a cell meant for a LUT: identified to a margin below its target
            options = options.model_copy(update={"stop_margin_db": LUT_MARGIN_DB})
        # points the envelope model refuses are stored failed with the reason and never run (a full-load curve
        # clipping the grid, service.model.limits.outside_envelope); the rest are measured
        inside = []
        for op in points:
            why = outside_envelope(op, self.settings, options.override_envelope_model)
            if why is None:
                inside.append(op)
            elif not ctl.cancel.is_set():
                self._store_not_run(sweep_id, ctl, op, self._not_run_row(op, sweep, options, why, sweep_id, tags))
        points = inside
        point: _PointInFlight | None = None
        i = 0
        while i < len(points):
            if ctl.cancel.is_set():
                break
            if ctl.pause.is_set():
                raise Paused()
            try:
                # the rows priors are read from (maps.neighbours reads dicts): read before each run (after a pause, a
                # failure, a store that did not answer), before the drive is enabled, then each point's stored result
                # added as the store gives it back (read for every point, a refinement's hundreds of results cost 245 s
                # of a 618 s refinement's wall at speedup 0, and held the DAQ unread in the open run)
                prior_rows = cast(list[dict[str, Any]], list(rows_for_priors()))
                with self.bench.run(cancel=ctl.cancel, **run_settings(self.settings, options)) as run:
                    while i < len(points) and not ctl.pause.is_set() and not ctl.cancel.is_set():
                        point = _PointInFlight(points[i], self.host.new_recorder())
                        try:
                            prior = prior_from_neighbours(point.op, prior_rows, grid.model_dump())
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
                        rid = self._store_point(sweep_id, point.op, row, point.recorder)
                        point = None
                        i += 1
                        prior_rows += cast(list[dict[str, Any]], list(self.storage.results_by_id([rid]).values()))
            except StorageUnavailable as exc:
                # the run has ended (bench made safe); the point measured is kept and written when the
                # database answers again, or measured again if it was not measured yet
                if self._storage_pause(sweep_id, ctl, exc, point):  # stored now
                    i += 1
                point = None
                continue
            except InterlockTripped as exc:
                # the point is measured again after the operator resumes; its attempt (if any
                # torque was commanded) is kept as a failed, discarded attempt, never ok
                if point is not None and not exc.refused:
                    self._store_point(
                        sweep_id,
                        point.op,
                        self._discarded_row(point.op, sweep, options, point.started, exc, sweep_id),
                        point.recorder,
                    )
                else:
                    discard_recorder(point.recorder if point is not None else None)
                at = point.op if point is not None else points[min(i, len(points) - 1)]
                self._pause_for_interlock(sweep_id, ctl, at, exc)
                point = None
                continue
            except Exception as exc:
                if ctl.cancel.is_set():
                    if point is None:
                        return None
                    discard_recorder(point.recorder)
                    return point.op
                if point is None:
                    raise  # the run itself could not start or end (bench not safe): the sweep fails
                # the bench failed during this point (the run ended, bench made safe): stored failed, next point
                log.warning("sweep %s point %s failed: %s", sweep_id, point.op.label(), exc)
                self._store_point(
                    sweep_id, point.op, self._failed_row(point, sweep, options, exc, sweep_id, tags), point.recorder
                )
                point = None
                i += 1
        return None

    def _failed_row(
        self,
        point: _PointInFlight,
        sweep: SweepRecord,
        options: MethodOptions,
        exc: BaseException,
        sweep_id: int,
        tags: dict[str, Any],
    ) -> dict[str, Any]:
        return result_row(
            point.op,
            sweep["method"],
            options,
            self.bench.identity,
            point.started,
            error=error_text(exc),
            sweep_id=sweep_id,
            harmonic_order=self.settings.identification.harmonic_order,
            detail={"message": error_text(exc), "details": dict(tags)},
        )

    def _not_run_row(
        self,
        op: OperatingPoint,
        sweep: SweepRecord,
        options: MethodOptions,
        why: str,
        sweep_id: int,
        tags: dict[str, Any],
    ) -> dict[str, Any]:
        """A point the envelope model refuses (service.model.limits.outside_envelope): failed, never run."""
        return result_row(
            op,
            sweep["method"],
            options,
            self.bench.identity,
            now_iso(),
            error=why,
            sweep_id=sweep_id,
            harmonic_order=self.settings.identification.harmonic_order,
            detail={"message": why, "details": {**tags, "not_run": "outside_envelope"}},
        )

    def _store_not_run(self, sweep_id: int, ctl: SweepControl, op: OperatingPoint, row: dict[str, Any]) -> None:
        """A point never run, stored failed with its reason; a database that cannot take it is waited for
        as for a measured point (_storage_pause: the sweep shown paused with the reason, the row written
        when the database answers again)."""
        try:
            self._store_point(sweep_id, op, row, None)
        except StorageUnavailable as exc:
            self._storage_pause(sweep_id, ctl, exc, _PointInFlight(op, None, row["started_at"], row))

    def _store_point(self, sweep_id: int, op: OperatingPoint, row: dict[str, Any], recorder: RunRecorder | None) -> int:
        """Store the point's result (and its recording); returns the result's id."""
        rid = self.host.insert_result(row, recorder)
        # the result by its id: the API's event stream shows it as a result (service/api/event_stream.py)
        self.broker.publish(
            "sweep.point",
            {"sweep_id": sweep_id, "operating_point": op.model_dump(), "state": row["status"], "result_id": rid},
        )
        self.host.publish_sweep(sweep_id)
        return rid

    def _discarded_row(
        self,
        op: OperatingPoint,
        sweep: SweepRecord,
        options: MethodOptions,
        started: str,
        exc: InterlockTripped,
        sweep_id: int,
    ) -> dict[str, Any]:
        return result_row(
            op,
            sweep["method"],
            options,
            self.bench.identity,
            started,
            error=error_text(exc),
            sweep_id=sweep_id,
            harmonic_order=self.settings.identification.harmonic_order,
            detail={"message": str(exc), "discarded": "interlock", "interlock": exc.trip.public()},
        )

    def _storage_pause(
        self, sweep_id: int, ctl: SweepControl, exc: StorageUnavailable, point: _PointInFlight | None
    ) -> bool:
        """The database cannot be used: the bench is already safe (the run ended). Tell the dashboard the
        sweep waits (in memory: the database cannot take it), keep the point measured and write it when the
        database answers again, then go on by itself. A cancel or a shutdown ends the wait. True: the
        point's row is stored now (False: there was none, or the wait ended before the database took it)."""
        measured = point if point is not None and point.row is not None else None
        reason = f"{exc.public} at {now_iso()}; " + (
            f"the point {measured.op.label()} is kept and written when it answers again"
            if measured is not None
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
        stored = False
        with self.host.waiting_for_storage(sweep_id, reason):
            if measured is not None and measured.row is not None:
                # kept even through a cancel: a point measured is never thrown away while the service runs
                op, row, recorder = measured.op, measured.row, measured.recorder
                stored = self.host.durably(
                    lambda: self._store_point(sweep_id, op, row, recorder),
                    f"sweep {sweep_id}: storing point {op.label()}",
                )
                if not stored:
                    discard_recorder(recorder)
            else:
                discard_recorder(point.recorder if point is not None else None)
                self.host.durably(
                    lambda: self.storage.get_sweep(sweep_id), f"sweep {sweep_id}: the database", ctl.cancel
                )
        self.host.publish_sweep(sweep_id)
        return stored

    def _pause_for_interlock(self, sweep_id: int, ctl: SweepControl, op: OperatingPoint, exc: InterlockTripped) -> None:
        reason = (
            f"{exc.trip.reason} during point {op.label()}"
            + (" (refused before it started)" if exc.refused else " (discarded; measured again on resume)")
            + (
                "; acknowledge with POST /api/v1/bench/fault-reset, then resume"
                if exc.trip.latched
                else "; resume when it has cleared"
            )
        )
        with self.host.lock:
            ctl.pause.set()
            self.host.set_sweep(sweep_id, SweepState.PAUSED, pause_reason=reason)
        log.warning("sweep %s paused: %s", sweep_id, reason)
        self.host.publish_sweep(sweep_id)


def stored_sweep(storage: Storage, sweep_id: int) -> SweepRecord:
    """The sweep a job or an action names, as stored (NotFound: the database holds no such sweep)."""
    sweep = storage.get_sweep(sweep_id)
    if sweep is None:
        raise NotFound(f"sweep {sweep_id} does not exist")
    return sweep


def job_sweep_id(job: JobRecord) -> int:
    """The sweep a sweep's job (of any kind) runs: its row names it from its creation (Engine.queue_sweep)."""
    sweep_id = job["sweep_id"]
    if sweep_id is None:
        raise ValueError(f"job {job['id']} of kind {job['kind']} names no sweep")
    return sweep_id


def stored_plan(sweep: SweepRecord) -> SweepPlan:
    """The plan a sweep was queued with (service/runs/kinds/sweep.py plans it once, at submit): its stored
    grid is the planned grid, and its points' order a function of that grid alone (SweepPlan.from_grid)."""
    return SweepPlan.from_grid(Grid.model_validate(sweep["grid"]))


def second_pass_points(plan: SweepPlan, current: list[ResultRecord]) -> list[OperatingPoint]:
    """The plan's points, in its order, whose current result is not ok and was not itself measured in
    the second pass (a resumed sweep does not measure a point a third time)."""
    again = set()
    for row in current:
        details = (row.get("detail") or {}).get("details") or {}
        if row["status"] != "ok" and details.get("sweep_pass") != 2:
            again.add((row["torque_nm"], row["speed_rpm"], row["udc_v"]))
    return [op for op in plan.points if (op.torque_nm, op.speed_rpm, op.udc_v) in again]


@dataclass
class _PointInFlight:
    """The sweep point being measured: its operating point, raw recorder and start time."""

    op: OperatingPoint
    recorder: RunRecorder | None
    started: str = field(default_factory=now_iso)
    row: dict[str, Any] | None = None  # its result, once measured (until stored)


def discard_recorder(recorder: RunRecorder | None) -> None:
    """A run that leaves no result (cancelled, refused) leaves no recording either."""
    if recorder is not None:
        recorder.close()


def error_text(exc: BaseException) -> str:
    """'Type: message' plus any notes (e.g. what failed after an interlock trip)."""
    text = f"{type(exc).__name__}: {exc}"
    notes = getattr(exc, "__notes__", None)
    return text + "".join(f"; {n}" for n in notes) if notes else text
