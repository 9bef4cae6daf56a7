"""The service layer: settings, storage, bench, engine and events wired together.

API routes and the CLI call this for what takes more than one part (a submission with its checks, a
download, a schedule, a sweep as its run sees it) and read the rest from the part that owns it
(`records`, `bench`, `engine`, `lab`); they hold no logic of their own. With `bench_mode = "emulate"`
the emulator is started as a child process and its endpoints fill the bench settings, so the rest
of the service sees only wires and settings strings.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from drivers.blas_threads import one_blas_thread
from drivers.errors import FaultReactionActiveError
from service import __version__
from service.bench.bench import Bench, BenchError, BenchUnreachable
from service.bench.emulator_process import EmulatorProcess
from service.errors import BenchFailed, Conflict, not_found
from service.runs import lut_download, schedules
from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.runs.lab import Lab, LabWatch, bench_state, new_instance_id
from service.runs.schedules import Clock, Scheduler, utc_now
from service.settings import Settings
from service.store.db_claim import DatabaseClaim
from service.store.engines import database_claim
from service.store.recordings import RecordingStore, RecordingUnavailable, recordings_directory
from service.store.records import SweepRecord
from service.store.storage import Storage

log = logging.getLogger(__name__)

# what the API and the CLI read stored rows through: the storage itself, whose reads return the records of
# service/store/records.py (its writes are the engine's, the schedules' and the lab's)
Records = Storage

LAB_PERIOD_S = 1.0  # the bench's heartbeat and the look at other benches' progress
# a shutdown's bounds (a database that hangs must not hold it: the bench is made safe before any of them)
STOP_WORKER_S = 2.0  # the engine's worker is waited for this long after its run was stopped
STOP_BOOKKEEPING_S = 2.0  # marking what was unfinished (the database) is given this long, then left to recovery
STOP_THREAD_S = 0.5  # each helper thread (scheduler, lab heartbeat) is waited for this long
STOP_NAME_S = 1.5  # freeing the bench's name (else it goes stale, and a restart may wait for that)


def settings_with_emulator(settings: Settings, endpoints: dict[str, Any]) -> Settings:
    can = endpoints["can"]
    return settings.model_copy(
        update={
            "can": settings.can.model_copy(
                update={
                    "interface": can["interface"],
                    "channel": can["channel"],
                    "host": can.get("host"),
                    "port": can.get("port"),
                    "drive_node": endpoints.get("drive_node", 5),
                    "load_node": endpoints.get("load_node", 6),
                }
            ),
            "daq": settings.daq.model_copy(
                update={
                    "url": endpoints["daq"],
                    "sample_rate_hz": endpoints.get("sample_rate_hz", settings.daq.sample_rate_hz),
                }
            ),
            "supply": settings.supply.model_copy(update={"url": endpoints["supply"]}),
        }
    )


class CalibrationService:
    def __init__(
        self,
        settings: Settings,
        clock: Clock = utc_now,
        storage: Storage | None = None,
        claim: DatabaseClaim | None = None,
    ):
        """`storage`: the database, already opened by the caller (the CLI opens it first, to name what is
        wrong with it in one line); else opened here, from settings.server.db_path. `claim`: the
        database's claim, already taken by the caller (the CLI takes it before even migrating)."""
        self.settings = settings
        self.clock = clock  # the scheduler's time (tests step a fake one)
        self.storage = (
            storage
            if storage is not None
            else Storage(
                settings.server.db_path,
                busy_timeout_s=settings.server.db_busy_timeout_s,
                statement_timeout_s=settings.server.db_statement_timeout_s,
            )
        )
        self.broker = EventBroker()
        self.emulator: EmulatorProcess | None = None
        self.bench: Bench | None = None
        self.engine: Engine | None = None
        self.recordings: RecordingStore | None = None
        self.scheduler: Scheduler | None = None
        self.version = __version__
        self._status_stop = threading.Event()
        self._status_thread: threading.Thread | None = None
        self.shutdown_reason = "service shut down"  # the CLI names the signal (e.g. SIGTERM)
        self.claim = claim
        self.instance = new_instance_id()  # this process in the lab's benches table (service/runs/lab.py)
        self.lab = Lab(self.storage, settings.bench_name, self.instance, settings.server.port, __version__)
        self._lab_thread: threading.Thread | None = None
        self._stop_lock = threading.Lock()
        self._stopped = False

    def start(self, status_period_s: float | None = 1.0, run_schedules: bool = True) -> None:
        """Start the emulator (emulate mode), connect the bench, start the engine and the status poller
        (every status_period_s, at a fixed rate: slow reads do not lower it).
        A real bench that cannot be reached is logged in one line and left disconnected: the service
        still comes up (dashboard, stored results, the reason in /bench/status) and refuses runs.
        `run_schedules`: fire due schedules and recover what a previous server left unfinished (the
        server does; a CLI run of one sweep does neither: a server may be running on the same database)."""
        one_blas_thread()
        settings = self.settings
        if run_schedules:
            self.claim_database()
            if not self.lab.claimed:  # the CLI claims it first (a refusal in one line, exit 2)
                self.lab.claim()  # BenchInUse naming the live holder: before recovery or the bench are touched
            # the heartbeat from the claim on (its own thread, not the status poller: a slow device read
            # must not let the bench look offline), so an emulator or bench slow to start keeps the name
            self._lab_thread = threading.Thread(
                target=self._lab_round, args=(LAB_PERIOD_S,), name="ripplecal-lab", daemon=True
            )
            self._lab_thread.start()
        identity = settings.bench_name
        if settings.bench_mode == "emulate":
            em = settings.emulator
            self.emulator = EmulatorProcess(em.scenario, em.seed, em.speedup, em.start_timeout_s)
            endpoints = self.emulator.start()
            settings = settings_with_emulator(settings, endpoints)
            identity = f"emulated:{endpoints.get('scenario', em.scenario)}" + (
                f":seed={em.seed}" if em.seed is not None else ""
            )
        self.settings = settings
        rec = settings.recordings
        self.recordings = RecordingStore(
            self.storage,
            recordings_directory(rec.directory, self.storage.files_directory),
            rec.keep_gb,
            settings.daq.sample_rate_hz,
            settings.daq.accel_full_scale_rad_s2,
            enabled=rec.enabled,
        )
        try:
            self.bench = Bench(settings, identity, on_trip=self._on_trip)
            try:
                self.bench.connect()
            except BenchUnreachable as exc:
                if self.emulator is not None:  # our own emulator not answering is a bug, not a bench to check
                    raise
                log.error("%s", exc)
            # a serve takes every job the database holds for its bench; a CLI run only what it queued
            self.engine = Engine(
                self.storage,
                self.bench,
                settings,
                self.broker,
                recordings=self.recordings,
                instance=self.instance,
                lab=run_schedules,
            )
            self.engine.start(recover=run_schedules)
            if run_schedules:
                self.scheduler = Scheduler(self.storage, self.engine, settings, self.broker, clock=self.clock)
                self.scheduler.start()  # its first pass handles the firings missed while the service was down
        except Exception:
            self.stop()
            raise
        if status_period_s:
            self._status_thread = threading.Thread(
                target=self._poll_status, args=(status_period_s,), name="ripplecal-status", daemon=True
            )
            self._status_thread.start()
        if run_schedules:
            self._heartbeat()  # the row says the bench's state as soon as the service is up, not a second later

    def claim_database(self) -> None:
        """The process that recovers the database's unfinished work claims it first (service/store/db_claim.py):
        DatabaseInUse naming the holder if another serve has it. Idempotent."""
        if self.claim is None:
            # a flock on a SQLite file; nothing on a shared server, where the lab's bench claim rules
            claim = database_claim(self.settings.server.db_path, self.settings.server.port)
            claim.acquire()
            self.claim = claim

    def stop_bench_now(self, reason: str | None = None) -> None:
        """Make the bench safe at once if a run holds it (the bench watchdog's thread acts): no lock, no I/O,
        never blocks, so a signal's first reaction may call it."""
        if self.bench is not None:
            self.bench.stop_now(reason or self.shutdown_reason)

    def stop(self) -> None:
        """Orderly, idempotent and bounded (a second call returns at once): the bench made safe first,
        whatever the worker is doing; then the worker waited for, with a timeout; what needs the database
        (marking unfinished work, freeing the bench's name) is given a bounded time, else left to the next
        start's recovery."""
        with self._stop_lock:
            if self._stopped:
                return
            self._stopped = True
        self._status_stop.set()
        self.stop_bench_now()
        if self.scheduler is not None:
            self.scheduler.stop(STOP_THREAD_S)  # first: no firing into an engine that is stopping
        if self.engine is not None:
            engine = self.engine
            _bounded(
                lambda: engine.stop(self.shutdown_reason, timeout_s=STOP_WORKER_S),
                STOP_WORKER_S + STOP_BOOKKEEPING_S,
                "the engine's stop",
            )
        if self.bench is not None:
            self.bench.close()  # leaves the bench safe (torque off, injection off), heartbeat consumers disarmed
        if self.emulator is not None:
            self.emulator.stop()
        if self._lab_thread is not None:
            # its heartbeat in flight must land before the name is freed, or it renews the name after it
            self._lab_thread.join(STOP_THREAD_S if self.storage.known_unavailable() else STOP_NAME_S)
        if self.storage.known_unavailable() is None:  # last: the name is free once the bench is safe
            _bounded(self.lab.stopped, STOP_NAME_S, "freeing the bench's name")
        else:
            log.warning("shutdown: the bench's name is not freed (the database does not answer): it goes stale")
        if self.claim is not None:
            self.claim.release()

    def now(self):
        """The scheduler's time: next_runs and the times a schedule records are counted from it."""
        return self.clock()

    def _on_trip(self, trip) -> None:
        """An interlock tripped (monitor/CAN thread): tell the dashboard at once."""
        self.broker.publish("bench.interlock", trip.public())

    def bench_check(self, spin: bool = False) -> dict:
        """The bring-up check (service/bench/bringup.py): {ok, checks: [{name, ok, detail, fix}]}. Conflict while a
        run holds the bench (its reads would interleave with the run's)."""
        from service.bench.bringup import check_bench

        if self.bench.busy:
            raise Conflict("the bench is busy with a run: check it when the run has ended")
        checks = [c.as_dict() for c in check_bench(self.bench, self.settings, spin)]
        return {"ok": all(c["ok"] for c in checks), "spin": spin, "checks": checks}

    def fault_reset(self) -> dict:
        """A person acknowledges a drive/load fault (POST /bench/fault-reset). Conflict: the bench is busy or
        a device is still braking (try again); BenchFailed: an SDO timeout, the drive stayed in FAULT."""
        try:
            result = self.bench.fault_reset()
        except BenchError:
            raise
        except FaultReactionActiveError as exc:
            raise Conflict(str(exc)) from None
        except Exception as exc:  # say which: the operator reads it at the bench
            raise BenchFailed(f"fault reset failed: {type(exc).__name__}: {exc}") from None
        self.broker.publish("bench.fault_reset", result)
        self.broker.publish("bench.status", self.bench.status())
        return result

    # --- what the API routes and the CLI call: what takes more than one part of the service -------------
    # (a plain read goes to the part that owns it: `records` for the stored rows, `bench`, `engine`, `lab`)
    @property
    def records(self) -> Records:
        """The stored records as the layers above read them (jobs, sweeps, results, maps, validations,
        schedules, tokens; service/store/records.py types each row)."""
        return self.storage

    def cancel_job(self, job_id: int) -> None:
        with not_found(f"job {job_id} does not exist"):
            self.engine.cancel_job(job_id)

    def control_sweep(self, sweep_id: int, action: str) -> None:
        """`action`: pause | resume | cancel."""
        with not_found(f"sweep {sweep_id} does not exist in this service run"):
            self.engine.control_sweep(sweep_id, action)

    def submit_validation(self, map_id: int, force: bool, options, bench: str | None = None) -> int:
        with not_found(f"map {map_id} does not exist"):
            return self.engine.submit("validation", map_id, force, options, bench=bench)

    def submit_refinement(self, map_id: int, request, bench: str | None = None) -> int:
        with not_found(f"map {map_id} does not exist"):
            return self.engine.submit("refinement", map_id, request, bench=bench)

    def download_map(self, map_id: int, force: bool, fill: bool = True, interpolation: str | None = None):
        try:
            return lut_download.download_map(
                self.storage, self.bench, map_id, force, fill=fill, interpolation=interpolation
            )
        except (lut_download.MapNotFound, lut_download.LutRefused, lut_download.PartialMap, BenchError):
            raise
        except Exception as exc:  # SDO abort / timeout: the drive refused or did not answer
            raise BenchFailed(f"drive refused the LUT: {exc}") from None

    def open_recording(self, result_id: int):
        """The result's raw recording, open for reading (RecordingUnavailable says why there is none)."""
        if self.recordings is None:
            raise RecordingUnavailable("recordings are not available: the service has not started")
        return self.recordings.open(result_id)

    def create_schedule(
        self, name: str, cron: str, timezone: str, sweep, enabled: bool, bench: str | None = None
    ) -> int:
        return schedules.create_schedule(
            self.storage, self.settings, self.now(), name, cron, timezone, sweep, enabled, bench=bench
        )

    def update_schedule(self, schedule_id: int, changes: dict[str, Any]) -> None:
        schedules.update_schedule(self.storage, self.settings, self.now(), schedule_id, changes)

    def delete_schedule(self, schedule_id: int) -> None:
        schedules.delete_schedule(self.storage, self.now(), schedule_id)

    # --- a stored sweep as its run sees it (the engine's view over the storage's row) --------------------
    def seen_sweep(self, sweep_id: int) -> SweepRecord | None:
        sweep = self.storage.get_sweep(sweep_id)
        return None if sweep is None else self._as_seen(sweep)

    def seen_sweeps(self, limit: int) -> list[SweepRecord]:
        return [self._as_seen(s) for s in self.storage.list_sweeps(limit)]

    def _as_seen(self, sweep: SweepRecord) -> SweepRecord:
        """A sweep whose run waits for the database shows paused with why (the engine holds it)."""
        return sweep if self.engine is None else self.engine.as_seen(sweep)

    def _poll_status(self, period_s: float) -> None:
        # fixed rate (not period + read time), so slow reads do not drop the rate below 1/period_s
        next_at = time.monotonic() + period_s
        while not self._status_stop.wait(max(0.0, next_at - time.monotonic())):
            next_at = max(next_at + period_s, time.monotonic())
            try:
                status = self.bench.refresh_status()
            except Exception:  # noqa: BLE001 - the live view must outlive one bad round
                log.exception("bench status round failed")
                continue
            self.broker.publish("bench.status", status)

    def _lab_round(self, period_s: float) -> None:
        """The bench's heartbeat in the benches table and the other benches' progress as events. Reads
        only the bench's cached status (no device I/O); a database away is logged, the bench untouched."""
        watch = LabWatch(self.storage, self.broker, self.settings.bench_name)
        while True:  # the first round at once: the name's row is renewed from the claim on
            self._heartbeat()
            try:
                watch.tick()
                if self.engine is not None:
                    self.engine.act_on_control_requests()  # pause / resume / cancel asked at other services
            except Exception as exc:  # noqa: BLE001 - the next round tries again
                log.debug("lab round failed: %s", exc)
            if self._status_stop.wait(period_s):
                return

    def _heartbeat(self) -> None:
        """The bench's row renewed with its state and what the engine runs (never raises)."""
        status = self.bench.status() if self.bench is not None else None
        running = self.engine.running if self.engine is not None else None
        state = bench_state(status, running) if status is not None and self.engine is not None else "starting"
        self.lab.heartbeat(state, running is not None or bool(status and status.get("busy")), running)

    def __enter__(self) -> "CalibrationService":
        self.start(status_period_s=None, run_schedules=False)
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _bounded(step, timeout_s: float, what: str) -> None:
    """Run `step` in a thread of its own and wait for it at most `timeout_s` (a shutdown must not wait on a
    database that hangs); an error or an overrun is logged, never raised."""

    def run() -> None:
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - a shutdown goes on whatever one step says
            log.warning("shutdown: %s failed: %s", what, exc)

    thread = threading.Thread(target=run, name=f"ripplecal-stop: {what}", daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        log.warning(
            "shutdown: %s did not end within %.0f s (the database does not answer?): left to the next start",
            what,
            timeout_s,
        )
