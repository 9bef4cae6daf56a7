"""The run lifecycle: opening a run, the commands sent during it, and ending it safe.

Safety (pymeasure's startup/execute/shutdown): every run ends in `make_safe` (torque off, injection
off, drive disabled, load stopped), also after an error or a cancel, and every wait has a timeout.
A run holds the bench (its lock) and arms the interlocks throughout (service/bench/faults.py); it
is refused, nothing commanded, while one is tripped. Before each run the setpoint/sync-toggle
accounting is re-established from the drive itself (commit counter read-back, DAQ quiet), so one
SDO timeout or a fault that dropped queued setpoints never poisons the runs after it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from typing import Callable, Iterator

from drivers.cia402 import State402
from drivers.errors import DaqError
from drivers.load_machine import LoadClient
from service.bench.connections import BenchLinks
from service.bench.contracts import RunBench
from service.bench.errors import BenchError, RunError
from service.bench.faults import BenchFaults, BenchInterlocks
from service.bench.measurement import OperatingPointSession, RunCancelled
from service.bench.run import BenchRun, gamma_max_for_run
from service.bench.run_commands import RunCommands
from service.bench.setpoint_accounting import AccountingError, SetpointAccounting
from service.bench.standstill import StandstillJudge
from service.bench.trips import InterlockTripped
from service.bench.watchdog import BenchWatchdog
from service.identification.session import Window
from service.model import limits
from service.model.harmonic import mechanical_speed_rpm
from service.model.operating_point import OperatingPoint
from service.settings import Settings

log = logging.getLogger(__name__)

MAX_BRAKE_PLANT_S = 60.0  # a shaft still braking after this long is stuck, whatever its progress


class RunLifecycle:
    """Runs on the bench (module doc). `after_run()` is called once a run has ended and the bench is
    released (the status view reads the state the run left)."""

    def __init__(
        self,
        settings: Settings,
        links: BenchLinks,
        faults: BenchFaults,
        lock: threading.RLock,
        after_run: Callable[[], None],
    ):
        self.settings = settings
        self.links = links
        self.faults = faults
        self._lock = lock
        self._after_run = after_run
        self._accounting: SetpointAccounting | None = None  # the drive's setpoints against the DAQ sync line
        self.busy = False
        self._run: BenchRun | None = None
        # makes the bench safe from its own thread when the run's loop goes silent or a stop is asked
        # (service/bench/watchdog.py); it reports through the faults' reporter (the service's SSE)
        self.watchdog = BenchWatchdog(
            lambda: links.drive,
            lambda: links.load,
            settings.interlocks.watchdog_s,
            on_stop=lambda trip: faults.on_trip(trip) if faults.on_trip is not None else None,
        )

    # --- the setpoint accounting -----------------------------------------------------------------------
    @property
    def accounting(self) -> SetpointAccounting:
        """The drive's setpoints against the DAQ sync line; BenchError before connect attached it."""
        if self._accounting is None:
            raise BenchError("the bench is not connected: its setpoints are not counted")
        return self._accounting

    def attach_accounting(self) -> None:
        """At connect: count the drive's setpoints against the DAQ's sync toggles from now on."""
        links = self.links.opened()
        drive = links.drive
        self._accounting = SetpointAccounting(
            links.daq,
            self.settings.daq.read_timeout_s,
            lambda: drive.setpoints_written,
            drive.resync_setpoint_count,
        )
        drive.on_setpoint = self._accounting.note_write

    def establish_accounting(self) -> None:
        """Learn the DAQ sync line at connect, so the first run does not wait for it; a DAQ that does
        not stream yet leaves it to the first run."""
        if not self.settings.daq.sync_input:
            return
        with self._lock:
            try:
                self.accounting.establish(guard=lambda: None)
            except (DaqError, AccountingError) as exc:
                log.warning("setpoint accounting not established at connect (the first run does it): %s", exc)

    # --- a run -----------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def run(
        self,
        bench: RunBench,
        harmonic_order: int,
        gamma_max_rad: float | None = None,
        decoupling: bool | None = None,
        cancel: threading.Event | None = None,
    ) -> Iterator[BenchRun]:
        """One continuous run (service/bench/run.py) on `bench`: the bench held, the interlocks armed
        throughout, moves from point to point; make_safe when it ends, however it ends. gamma_max_rad
        (default: settings) is enforced here and also set in the drive, which clamps; decoupling
        (default: settings) is the drive's 0x2000:6 for the run. Refused (InterlockTripped, nothing
        commanded) while an interlock is tripped. `cancel` set stops the run at its next DAQ read."""
        if not self.faults.connected:
            raise InterlockTripped(self.links.unreachable_trip(), refused=True)
        with self._lock:
            self.faults.refuse_or_auto_reset()
            # connected (checked above): every link, the interlocks and the accounting are there
            links, interlocks, accounting = self.links.opened(), self.faults.started(), self.accounting
            self.busy = True
            commands = RunCommands(
                self.settings,
                links.drive,
                links.load,
                links.supply,
                self.faults,
                self.watchdog,
                gamma_max_for_run(gamma_max_rad, limits.gamma_max_rad(None, self.settings)),
                cancel,
            )
            run = BenchRun(
                bench,
                commands,
                harmonic_order,
                self.settings.identification.decoupling if decoupling is None else decoupling,
            )
            self._run = run
            interlocks.monitor.arm()
            self.watchdog.arm()
            first: BaseException | None = None
            try:
                accounting.start_run(run.guard)
                yield run
            except BaseException as exc:
                first = exc
            self._end_run(first, interlocks, accounting)

    @contextlib.contextmanager
    def operating_point(
        self,
        bench: RunBench,
        op: OperatingPoint,
        harmonic_order: int,
        gamma_max_rad: float | None = None,
        cancel: threading.Event | None = None,
        on_window: Callable[[Window], None] | None = None,
        decoupling: bool | None = None,
        target_db: float = 40.0,
    ) -> Iterator[OperatingPointSession]:
        """A run of one point: go to `op`, settle, yield the session; the bench is left safe after it."""
        with self.run(bench, harmonic_order, gamma_max_rad, decoupling, cancel) as run:
            with run.operating_point(op, target_db=target_db, on_window=on_window) as session:
                yield session

    def _end_run(
        self, first: BaseException | None, interlocks: BenchInterlocks, accounting: SetpointAccounting
    ) -> None:
        """After a run (clean or not): learn whether an interlock is the first cause, make safe, and
        raise what happened: the trip (with make_safe's outcome), else the run's own error (with
        make_safe's error added if it failed too), else make_safe's error."""
        monitor = interlocks.monitor
        # before make_safe: its braking reads the DAQ without kicking, and the run's own stop follows
        self.watchdog.disarm()
        try:
            if first is not None and not isinstance(first, (RunCancelled, GeneratorExit)):
                monitor.check_now(force=True)  # an EMCY/FAULT may be why the run failed
            trip = monitor.disarm()
            if trip is not None:
                accounting.doubt("an interlock tripped during the run")  # a faulted drive drops what it queued
            interlocks.supply.expected_v = None
            safe_error: Exception | None = None
            try:
                self.make_safe()
            except Exception as exc:
                safe_error = exc
            accounting.end_run()
        finally:
            self.busy = False
            self._run = None
            self._after_run()
        outcome = "bench made safe" if safe_error is None else f"make_safe failed: {safe_error}"
        if trip is not None and not isinstance(first, GeneratorExit):
            err = InterlockTripped(trip, outcome=outcome)
            if first is not None and not isinstance(first, InterlockTripped):
                err.add_note(f"the run then failed with {type(first).__name__}: {first}")
            raise err from first
        if first is not None:
            if safe_error is None:
                raise first
            raise RunError(f"{type(first).__name__}: {first}; then {outcome}") from first
        if safe_error is not None:
            raise BenchError(f"bench may not be safe: {safe_error}") from safe_error

    # --- safe --------------------------------------------------------------------------------------------
    def make_safe(self, standstill_timeout_plant_s: float = 5.0, lock_timeout_s: float | None = None) -> None:
        """Torque off, injection off, drive disabled, load stopped; then wait (on the DAQ clock, or on
        the load's own speed reading if the DAQ is gone; bounded) for standstill. Tries every step,
        raises the first error. `lock_timeout_s`: wait no longer for the bench's run lock (a shutdown
        whose worker is stuck inside a run: the watchdog has made the bench safe without it)."""
        drive, load, accounting = self.links.drive, self.links.load, self._accounting
        errors: list[Exception] = []
        steps: list[Callable[[], object]] = []
        if drive is not None:
            steps.append(drive.disable)  # target torque 0, injection off, disable voltage
        if load is not None:
            steps.append(load.brake_to_standstill)  # at the full ramp, whatever a run-up set
            if accounting is not None:
                # brake with the load's speed loop before disabling it (a disabled load coasts)
                steps.append(lambda: self._wait_standstill(accounting, load, standstill_timeout_plant_s))
            steps.append(load.disable)
        if not self._lock.acquire(timeout=-1 if lock_timeout_s is None else lock_timeout_s):
            raise BenchError(
                f"make_safe: the run lock is still held after {lock_timeout_s:g} s (a worker stuck in a run); "
                "the bench watchdog disabled drive and load without it"
            )
        try:
            for step in steps:
                try:
                    step()
                except Exception as exc:
                    errors.append(exc)
                    log.error("make_safe step failed: %s", exc)
        finally:
            self._lock.release()
        if errors:
            raise BenchError(f"bench may not be safe: {errors[0]}") from errors[0]

    def _wait_standstill(self, accounting: SetpointAccounting, load: LoadClient, timeout_plant_s: float) -> None:
        """Consume the DAQ until the encoder shows the shaft at standstill (service/bench/standstill.py: below
        20 rpm for 0.25 s, not the speed loop's overshoot through zero), bounded on the DAQ clock: while the load
        brakes on its speed loop the bound counts from the last time the shaft had slowed by a fifth (a load
        braking from 3200 rpm at its own ramp takes longer than the bound, and is braking, not stuck), never past
        MAX_BRAKE_PLANT_S; a load that is not enabled does not brake (the shaft coasts), so the bound alone.
        Without a DAQ, poll the load machine's velocity actual instead (wall clock, the bound alone)."""
        rate = self.settings.daq.sample_rate_hz
        block = int(0.02 * rate)
        cursor = accounting.cursor
        judge = StandstillJudge()
        extend = _braking(load)
        try:
            start = None
            slowed_at, slowest_rpm = 0, math.inf
            while start is None or (
                cursor.last_index - slowed_at < timeout_plant_s * rate
                and cursor.last_index - start < MAX_BRAKE_PLANT_S * rate
            ):
                chunk = cursor.read(block).samples
                if start is None:
                    start = slowed_at = int(chunk.index[0])
                try:  # over the block's contiguous runs: the angle's step across a DAQ gap is unknown
                    speed_rpm = mechanical_speed_rpm(
                        chunk.angle_rad, rate, self.settings.motor.pole_pairs, chunk.gap_before
                    )
                except ValueError:
                    continue
                if judge.update(int(chunk.index[-1]) / rate, speed_rpm):
                    return
                if extend and abs(speed_rpm) < 0.8 * slowest_rpm:  # still braking: the bound counts from here
                    slowed_at, slowest_rpm = int(chunk.index[-1]), abs(speed_rpm)
        except DaqError as exc:
            log.warning("standstill judged on the load's speed: DAQ unavailable (%s)", exc)
            accounting.doubt("the DAQ was unavailable at the end of a run")
            deadline, judge = time.monotonic() + timeout_plant_s, StandstillJudge()  # its clock: wall time
            while time.monotonic() < deadline:
                if judge.update(time.monotonic(), load.read_status().speed_rpm):
                    return
                time.sleep(0.02)
        raise BenchError(
            f"shaft still turning {timeout_plant_s:g} s (plant time, DAQ sample clock) after it last slowed, after "
            "the stop command"
        )


def _braking(load: LoadClient) -> bool:
    """Whether the load brakes the shaft on its speed loop (enabled); unreadable counts as not (the bound
    alone then, never the extension)."""
    try:
        return load.state() == State402.OPERATION_ENABLED
    except Exception:  # noqa: BLE001 - the wait is bounded either way
        return False
