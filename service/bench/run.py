"""One continuous run on the bench: the drive enabled and the load machine turning from point to point.

A run is opened by `Bench.run` (which holds the bench, arms the interlocks, and makes the bench safe
when the run ends, however it ends: torque off, injection off, drive disabled, load stopped). Inside
it, `BenchRun.operating_point(op)` moves to the next point and yields a measurement session; the
bench is NOT made safe between points: a sweep or a validation is one run, so each point costs its
move (a torque step, a speed ramp), its settling and its measurement, not a stop and a new start.

The move to a point, in the order the wires need:
  1. the DC link: the supply set and confirmed (torque off first while a run changes U_dc);
  2. the load machine's speed (enabled at the run's first point); the drive enabled, gamma_max;
  3. the setpoint accounting re-established if it is in doubt (service/bench/setpoint_accounting.py): with
     nothing written that the drive applies, while the load ramps;
  4. what the drive applies as setpoints (each one sync toggle): at the run's first point harmonic
     order, decoupling, injection mode manual; theta 0 where it is not; and the torque, always: its
     toggle marks the sample from which every setpoint of the move is in force (the drive applies
     them in the order written).
Then the session settles by measurement (OperatingPointSession.settle_operating_point), and the drive's
torque actual (0x6077) is read: a point where it falls short of the command by more than half (or has
the other sign) is one the machine cannot reach at this speed and U_dc (past full field weakening the
current controller sits in its voltage limit and the motor may even brake against its command): it
fails with that reason instead of being calibrated at an operating point that is not the one asked
for. The margin is wide because 0x6077 is the drive's estimate from its nominal parameters. A failure
before the session is handed out names the move. From there on the drive's torque actual TPDOs are
averaged (`torque_actual`): what a result records as the torque it ran at, judged against its command
with the narrower safety.torque_tolerance_* (service/runs/identify.py hold_to_command).

Each point's wall time is split (PointTiming): move (commands until the last setpoint is written),
accounting, settle (from there to steady), measurement (the caller's use of the session).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Iterator, TypeVar, cast

from service.bench.contracts import RunBench
from service.bench.measurement import OperatingPointSession, SessionSettings
from service.bench.point_stream import PointStream
from service.bench.run_commands import RunCommands
from service.bench.trips import InterlockTripped, Trip
from service.identification.session import MeasurementError, Window
from service.model.limits import LimitError, check_limits
from service.model.operating_point import OperatingPoint

log = logging.getLogger(__name__)

# torque actual below this share of the command (or of the other sign): the point is not reached
TORQUE_REACHED_FRACTION = 0.5
TORQUE_CHECK_MIN_NM = 0.2  # below this command the estimate's offset says nothing
READ_WHILE_WORKING_S = 0.01  # reading_while: the DAQ is read this often (wall), well inside the reader's queue
READ_WHILE_WORKING_SAMPLES = 65536
T = TypeVar("T")


def torque_reached(command_nm: float, actual_nm: float) -> bool:
    """Whether the drive's torque actual shows the commanded torque (module doc)."""
    if abs(command_nm) < TORQUE_CHECK_MIN_NM:
        return True
    return actual_nm * math.copysign(1.0, command_nm) >= TORQUE_REACHED_FRACTION * abs(command_nm)


@dataclass
class PointTiming:
    """Wall seconds of one point of a run, by what they were spent on."""

    move_s: float = 0.0
    accounting_s: float = 0.0
    settle_s: float = 0.0
    measurement_s: float = 0.0

    def public(self) -> dict[str, float]:
        return {k: round(v, 4) for k, v in asdict(self).items()}


class BenchRun:
    """A run in progress (module doc). Created by the run lifecycle only, given the bench as a RunBench
    (service/bench/contracts.py) and the run's commands (service/bench/run_commands.py), the one way down to
    the hardware, which its sessions send through too."""

    def __init__(self, bench: RunBench, commands: RunCommands, harmonic_order: int, decoupling: bool):
        self.bench = bench
        self.commands = commands
        self.harmonic_order = harmonic_order
        self.decoupling = decoupling
        self.at: OperatingPoint | None = None  # where the run stands (None: not moved yet)
        self.points = 0
        self.timing = PointTiming()  # of the last point
        self.accounting_reports: list[dict[str, Any]] = []

    def guard(self) -> None:
        self.commands.guard()

    def reading_while(self, work: Callable[[], T]) -> T:
        """`work()` (seconds of computing inside the open run, between points: a run-up's order analysis) done in a
        thread while this one goes on reading the DAQ and dropping what it reads, the run's guard checked between
        reads (interlocks, cancel, the watchdog kicked). Unread for seconds, a DAQ at a real bench's clock overflows
        (the reader's queue is full: whole frames lost), and the sync toggles of the next point's setpoints fall
        into that hole, where their count can go wrong (measured: a validation's run-up pairs at speedup 1 failed
        with "more sync toggles seen than setpoints written" after the analysis of the pair before). Nothing is
        written meanwhile, so no toggle is due; one seen is counted as any is."""
        done = threading.Event()
        outcome: dict[str, Any] = {}

        def target() -> None:
            try:
                outcome["value"] = work()
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                outcome["error"] = exc
            finally:
                done.set()

        threading.Thread(target=target, name="ripplecal-run-work", daemon=True).start()
        cursor = self.bench.accounting.cursor
        while not done.wait(READ_WHILE_WORKING_S):
            self.guard()
            cursor.read_available(READ_WHILE_WORKING_SAMPLES)
        if "error" in outcome:
            raise outcome["error"]
        return cast(T, outcome["value"])

    # --- points --------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def operating_point(
        self, op: OperatingPoint, target_db: float = 40.0, on_window: Callable[[Window], None] | None = None
    ) -> Iterator[OperatingPointSession]:
        """Move to `op` and settle (module doc), then yield a session whose plant time starts at zero.
        An interlock that tripped during the point ends it in InterlockTripped even if the caller
        finished: its data are not good. After an error the drive's theta and mode are unknown (the
        next move writes them again) and setpoints left unconfirmed put the accounting in doubt."""
        check_limits(op, self.bench.settings)
        self.timing = timing = PointTiming()
        bench, s = self.bench, self.bench.settings
        stream = PointStream(bench.accounting, s.daq.sample_rate_hz, guard=self.guard)
        settings = SessionSettings(
            self.harmonic_order,
            s.motor.pole_pairs,
            sync_input=s.daq.sync_input,
            no_sync_settle_s=s.daq.no_sync_settle_s,
        )
        session = OperatingPointSession(
            stream, self.commands, settings, bench.resonance, observe=bench.live.publisher("run"), on_window=on_window
        )
        bench.live.publish(
            "run", operating_point=op.model_dump(), speed_rpm=None, harmonic_amplitude_fs=None, plant_time_s=None
        )
        try:
            try:
                self._move(op, timing)
                commands = self.commands
                session.theta_in_force = commands.theta if commands.mode == "manual" else None
                session.further_in_force = commands.further if commands.mode == "manual" else None
                t0 = time.perf_counter()
                session.settle_operating_point(op.speed_rpm, target_db)
                actual_nm = self.commands.torque_actual_nm()
                if not torque_reached(op.torque_nm, actual_nm):
                    raise MeasurementError(
                        f"the drive does not reach {op.torque_nm:g} Nm here: its torque actual reads "
                        f"{actual_nm:.2f} Nm (the machine is past its voltage and current limits at this speed "
                        f"and U_dc); nothing is calibrated at a point the motor does not run at"
                    )
                timing.settle_s = time.perf_counter() - t0
            except MeasurementError as exc:
                raise MeasurementError(f"moving to {op.label()}: {exc}", over_range=exc.over_range) from exc
            except Exception as exc:
                exc.add_note(f"while moving to {op.label()}")
                raise
            session.reset_plant_time()
            if bench.actuals is not None:
                bench.actuals.start_mean()  # the point's torque actual: over its measurement from here
            self.points += 1
            t0 = time.perf_counter()
            try:
                yield session
            finally:
                timing.measurement_s = time.perf_counter() - t0
            # the supply is read every 0.5 s: a point shorter than that is checked before it counts
            trip = bench.interlocks.check(bench.supply_interlock)
            if trip is not None:
                raise InterlockTripped(trip)
        except BaseException as exc:
            self.commands.forget()
            if bench.accounting.pending() != 0:
                bench.accounting.doubt("a point ended with setpoints unconfirmed")
            if isinstance(exc, Exception) and not isinstance(exc, InterlockTripped):
                # a fault shows first as a measurement gone wrong (a drive that faulted, a supply that dropped:
                # torque actual reads 0, the DC link does not come up): the trip, if any, is the cause
                trip = self._first_trip()
                if trip is not None:
                    raise InterlockTripped(trip) from exc
            raise

    def torque_actual(self) -> tuple[float | None, int]:
        """The torque the point in progress runs at: the mean torque actual of the drive's TPDOs from the end of
        its settling on, and how many it averages. A measurement shorter than the TPDO period (the emulator
        running faster than real time) is read once by SDO instead (count 0), at the point."""
        actuals = self.bench.actuals
        mean_nm, count = actuals.mean_torque() if actuals is not None else (None, 0)
        if count == 0:
            mean_nm = self.commands.torque_actual_nm()
        return mean_nm, count

    def _first_trip(self) -> Trip | None:
        """The run's first interlock trip, every interlock read now rather than at its next period (the
        supply's is 0.5 s: a point can fail on its consequence before the monitor reads it)."""
        interlocks = self.bench.interlocks
        if interlocks is None:
            return None
        try:
            return interlocks.check_now(force=True)
        except Exception as exc:  # noqa: BLE001 - a reading that fails here leaves the monitor's word
            log.warning("interlocks not read on a point's error path: %s", exc)
            return interlocks.run_trip

    def _move(self, op: OperatingPoint, timing: PointTiming) -> None:
        bench, commands = self.bench, self.commands
        t0 = time.perf_counter()
        at, self.at = self.at, None  # unknown until the move is through
        first = at is None  # the run's first move, or the first after an error: everything is written again
        if first:
            commands.forget()
        # what the hardware was last told decides (a run-up leaves the shaft at its ramp's end, not at its point)
        if commands.udc_v != op.udc_v:
            commands.set_dc_link(op.udc_v)  # torque off first once any was commanded
        if first:
            commands.enable_load()
        if commands.speed_rpm != op.speed_rpm:
            commands.set_speed_rpm(op.speed_rpm)
        if first:
            commands.enable_drive()
        if bench.accounting.in_doubt:
            t1 = time.perf_counter()
            self.accounting_reports.append(bench.accounting.establish(self.guard))
            timing.accounting_s = time.perf_counter() - t1
        if first:
            commands.configure_injection(self.harmonic_order, self.decoupling)
        if commands.mode != "manual":
            commands.send_injection_mode("manual")
        if commands.theta != (0.0, 0.0) or commands.further != ():
            commands.send_theta(0.0, 0.0)
        # always written: its toggle marks the sample from which the whole move is in force
        commands.set_torque_nm(op.torque_nm)
        self.at = op
        timing.move_s = time.perf_counter() - t0 - timing.accounting_s


def gamma_max_for_run(requested_rad: float | None, settings_limit_rad: float) -> float:
    """The run's injection limit: the request's, never above the bench's."""
    if requested_rad is not None and (not math.isfinite(requested_rad) or requested_rad <= 0):
        raise LimitError(f"gamma_max {requested_rad!r} rad is not a positive number")
    return min(requested_rad or math.inf, settings_limit_rad)
