"""Interlocks: conditions under which no torque may flow, watched during every run (and between runs).

Modelled on bluesky's suspenders (bluesky/suspenders.py: SuspenderBase with `_should_suspend`,
`_should_resume`, `_get_justification`): each `Interlock` reads one signal of the bench, says whether
that value trips it and whether it has cleared, and justifies a trip in words an operator can act on
("EMCY 0x3210 DC link over-voltage", "heartbeat of drive node 5 lost", "DAQ ... disconnected").
Unlike a suspender, a trip never resumes a run by itself: the measurement in flight is discarded and a
sweep pauses; a *latched* interlock (drive FAULT/EMCY) also stays tripped until a person acknowledges
it (POST /bench/fault-reset), the others clear when their condition does.

`InterlockMonitor` polls the interlocks from its own thread (EMCY and the drive's actuals arrive pushed,
from the CAN receive thread, and are decided there at once), keeps the first trip of the run in flight (`run_trip`, read by the bench's guard before every
DAQ read) and calls `on_trip` at once, so the bench goes safe without waiting for the run to notice.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from typing import Any, Callable

from drivers.cia402 import State402
from drivers.emcy_codes import describe_emcy
from service.errors import BenchRefused

log = logging.getLogger(__name__)

_NO_READING = object()


@dataclass(frozen=True)
class Trip:
    """One interlock trip: which interlock, why (the first cause), whether a person must acknowledge it."""

    interlock: str
    reason: str
    latched: bool
    at: str  # ISO 8601 UTC
    monotonic: float

    def public(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("monotonic")
        return d


class InterlockTripped(BenchRefused, RuntimeError):
    """A run stopped (or was refused) because an interlock tripped; str() is the first cause."""

    def __init__(self, trip: Trip, refused: bool = False, outcome: str | None = None):
        self.trip = trip
        self.refused = refused
        self.outcome = outcome  # make_safe's outcome, added to (never substituted for) the cause
        prefix = "refused: interlock tripped: " if refused else "interlock tripped: "
        # only a person clears a latched trip: a refusal says how
        hint = "; a person acknowledges it: POST /api/v1/bench/fault-reset" if refused and trip.latched else ""
        super().__init__(prefix + trip.reason + hint + (f"; {outcome}" if outcome else ""))


class Interlock(ABC):
    """One watched condition (a suspender). `period_s`: how often the monitor reads it (reads that
    cost a bus round trip are spaced out); `armed_only`: watched only while a run holds the bench."""

    name = "interlock"
    latched = False
    period_s = 0.0
    armed_only = False

    def __init__(self) -> None:
        self.reason: str | None = None  # set while tripped
        self._next_read = 0.0

    @abstractmethod
    def read(self) -> Any:
        """The watched value; raise to say it could not be read (no decision this time)."""

    @abstractmethod
    def should_trip(self, value: Any) -> bool: ...

    def should_clear(self, value: Any) -> bool:
        return not self.should_trip(value)

    @abstractmethod
    def justification(self, value: Any) -> str: ...

    def due(self, now: float) -> bool:
        if now < self._next_read:
            return False
        self._next_read = now + self.period_s
        return True

    def armed_changed(self, armed: bool) -> None:
        """The monitor armed (a run started) or disarmed (it ended); an interlock that watches runs only listens."""

    def evaluate(self) -> str | None:
        """Read and decide; returns the reason while tripped. A latched trip is kept until reset()."""
        try:
            value = self.read()
        except Exception as exc:  # noqa: BLE001 - an unreadable signal decides nothing (its own interlock covers the link)
            log.debug("%s: cannot read: %s", self.name, exc)
            return self.reason
        return self.decide(value)

    def decide(self, value: Any) -> str | None:
        """Decide on a value (read, or pushed: InterlockMonitor.pushed); returns the reason while tripped."""
        if self.should_trip(value):
            if self.reason is None:
                self.reason = self.justification(value)
        elif self.reason is not None and not self.latched and self.should_clear(value):
            self.reason = None
        return self.reason

    def reset(self) -> str | None:
        """A person's acknowledgement: clears a latched trip if the condition has gone; returns the
        reason if it is still there."""
        self.reason = None
        return self.evaluate()


class DeviceFault(Interlock):
    """A CiA 402 device in FAULT, or an EMCY from it (pushed): latched until fault reset."""

    latched = True
    period_s = 0.25

    def __init__(self, device):
        super().__init__()
        self.device = device
        self.name = f"{device.device_kind}_fault"

    def read(self) -> State402:
        return self.device.state()

    def should_trip(self, value: State402) -> bool:
        return value in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)

    def justification(self, value: State402) -> str:
        return self.device.fault_description()

    def on_emcy(self, code: int) -> str | None:
        """An EMCY frame: trips (latched) unless it is an error reset (high byte 0)."""
        if code & 0xFF00 == 0:
            return None
        reason = f"{describe_emcy(code)} from {self.device.device_kind} node {self.device.node_id}"
        if self.reason is None:
            self.reason = reason
        return reason


class HeartbeatLost(Interlock):
    """The device's heartbeat has not been seen for 3 of its periods (the device or the bus is gone)."""

    def __init__(self, device):
        super().__init__()
        self.device = device
        self.name = f"{device.device_kind}_heartbeat"

    def read(self) -> tuple[bool, float | None]:
        return self.device.heartbeat_alive(), self.device.heartbeat_age_s()

    def should_trip(self, value) -> bool:
        return not value[0]

    def justification(self, value) -> str:
        age = value[1]
        seen = "never seen" if age is None else f"last seen {age:.1f} s ago"
        return f"heartbeat lost: {self.device.device_kind} node {self.device.node_id} ({seen})"


class ServiceHeartbeatStopped(Interlock):
    """Our own heartbeat is not being produced: the drive will fall to FAULT within its consumer time."""

    name = "service_heartbeat"

    def __init__(self, bus):
        super().__init__()
        self.bus = bus

    def read(self) -> bool:
        return self.bus.heartbeat_producing()

    def should_trip(self, value: bool) -> bool:
        return not value

    def justification(self, value) -> str:
        return f"heartbeat lost: the service's own heartbeat (node {self.bus.service_node_id}) is not being produced"


class DaqLost(Interlock):
    """The DAQ port is gone (unplugged, EOF/EIO), or a sample carries the sensor-fault flag."""

    name = "daq"

    def __init__(self, reader):
        super().__init__()
        self.reader = reader
        self._faults_seen: int | None = None

    def read(self) -> tuple[bool, int, str | None]:
        h = self.reader.health()
        return h["connected"], h.get("sensor_fault_samples", 0), h["last_error"]

    def should_trip(self, value) -> bool:
        connected, faults, _ = value
        new_faults = self._faults_seen is not None and faults > self._faults_seen
        self._faults_seen = faults
        self._new_faults = new_faults
        return not connected or new_faults

    def justification(self, value) -> str:
        connected, _, error = value
        if not connected:
            return daq_disconnected_reason(self.reader.url, error)
        return f"DAQ {self.reader.url}: sensor fault flag set"


def daq_disconnected_reason(url: str, error: str | None) -> str:
    return f"DAQ {url} disconnected ({error})"


class ForeignMaster(Interlock):
    """Another master on the CAN bus with the service's own node id (its heartbeat heard): SDO answers
    would cross and the drive would keep a dead service's heartbeat alive. Clears when it is gone."""

    name = "foreign_master"
    period_s = 0.5

    def __init__(self, bus):
        super().__init__()
        self.bus = bus

    def read(self) -> str | None:
        return self.bus.foreign_master()

    def should_trip(self, value: str | None) -> bool:
        return value is not None

    def justification(self, value: str) -> str:
        return f"a second master on the bus: {value}; stop it (one service per bench)"


class SupplyOutOfRange(Interlock):
    """The DC supply measures outside a band around the voltage the run set (only during a run)."""

    name = "supply"
    period_s = 0.5
    armed_only = True

    def __init__(self, supply, tolerance_fraction: float = 0.1, tolerance_v: float = 0.5):
        super().__init__()
        self.supply = supply
        self.tolerance_fraction = tolerance_fraction
        self.tolerance_v = tolerance_v
        self.expected_v: float | None = None  # set by the bench once the supply has reached it

    def band(self, expected_v: float) -> float:
        return max(self.tolerance_fraction * abs(expected_v), self.tolerance_v)

    def read(self) -> tuple[float, float] | None:
        """(measured, expected) read together: the bench clears expected_v at the end of a run, from
        another thread, between this read and the decision."""
        expected_v = self.expected_v
        if expected_v is None:
            return None
        return self.supply.measure_voltage(), expected_v

    def should_trip(self, value) -> bool:
        return value is not None and abs(value[0] - value[1]) > self.band(value[1])

    def should_clear(self, value) -> bool:
        return value is None or abs(value[0] - value[1]) <= 0.5 * self.band(value[1])  # hysteresis

    def justification(self, value) -> str:
        measured_v, expected_v = value
        return (
            f"DC supply out of range: measures {measured_v:.2f} V, set {expected_v:.2f} V "
            f"(band +-{self.band(expected_v):.2f} V)"
        )


class ActualsOutsideLimits(Interlock):
    """The envelope held on what the motor does: the drive's actuals (torque, current and speed actual, its TPDO
    every 10 ms, pushed from the CAN receive thread and decided at once: InterlockMonitor.pushed) against the
    hard limits and the torque sign, during every run. Setpoints are checked before they are sent; this is
    for a motor that leaves them (past full field weakening the inverter's diodes rectify and the machine
    brakes uncontrolled, at currents far above i_max). Margins (settings.safety): torque beyond max_torque_nm
    by actuals_margin_fraction, of the forbidden sign beyond that fraction of max_torque_nm, speed beyond
    max_speed_rpm by that fraction; current above current_trip_fraction x motor.i_max_a. During a run, actuals
    older than `stale_s` trip too (the drive stopped telling what it does). Latched: a person looks at a
    machine that ran away before it runs again.

    It also keeps the mean torque actual from `start_mean()` on (a point's measurement: `mean_torque()`)."""

    name = "actuals"
    latched = True
    period_s = 0.1  # the poll decides on staleness only: the values are decided as they arrive

    def __init__(self, drive, safety, i_max_a: float, stale_s: float = 1.0):
        super().__init__()
        self.drive = drive
        self.safety = safety
        self.i_max_a = i_max_a
        self.stale_s = stale_s
        self._watching = False
        self._since = 0.0  # monotonic: actuals before this are not the run's
        self._mean_lock = threading.Lock()
        self._sum_nm, self._count = 0.0, 0

    def armed_changed(self, armed: bool) -> None:
        self._watching = armed
        self._since = time.monotonic()

    def read(self):
        return self.drive.actuals

    def push(self, actuals) -> None:
        """A new TPDO of the actuals (CAN receive thread): counted into the mean (the decision is the monitor's)."""
        with self._mean_lock:
            self._sum_nm += actuals.torque_nm
            self._count += 1

    def start_mean(self) -> None:
        with self._mean_lock:
            self._sum_nm, self._count = 0.0, 0

    def mean_torque(self) -> tuple[float | None, int]:
        """(mean torque actual since start_mean, Nm, or None without any; how many TPDOs it averages)."""
        with self._mean_lock:
            return (self._sum_nm / self._count if self._count else None), self._count

    def _stale_s(self, actuals) -> float | None:
        if not self._watching:
            return None
        age = time.monotonic() - (self._since if actuals is None else max(actuals.received_at, self._since))
        return age if age > self.stale_s else None

    def _violation(self, actuals) -> str | None:
        s, m = self.safety, self.safety.actuals_margin_fraction
        if actuals is None:
            return None
        if abs(actuals.current_a) > s.current_trip_fraction * self.i_max_a:
            return (
                f"current actual {actuals.current_a:.1f} A above {s.current_trip_fraction:g} x motor.i_max_a = "
                f"{s.current_trip_fraction * self.i_max_a:.1f} A"
            )
        if abs(actuals.torque_nm) > s.max_torque_nm * (1.0 + m):
            return f"torque actual {actuals.torque_nm:.2f} Nm beyond the limit of {s.max_torque_nm:g} Nm (safety.max_torque_nm)"
        forbidden = {"positive": -1.0, "negative": 1.0}.get(s.torque_sign)
        if forbidden is not None and actuals.torque_nm * forbidden > m * s.max_torque_nm:
            return f"torque actual {actuals.torque_nm:.2f} Nm: this bench allows {s.torque_sign} torque only (safety.torque_sign)"
        if abs(actuals.speed_rpm) > s.max_speed_rpm * (1.0 + m):
            return f"speed actual {actuals.speed_rpm:.0f} rpm beyond the limit of {s.max_speed_rpm:g} rpm (safety.max_speed_rpm)"
        return None

    def should_trip(self, actuals) -> bool:
        return self._violation(actuals) is not None or self._stale_s(actuals) is not None

    def justification(self, actuals) -> str:
        violation = self._violation(actuals)
        if violation is not None:
            return (
                f"the motor left the envelope: {violation} (drive node {self.drive.node_id}: torque "
                f"{actuals.torque_nm:.2f} Nm, current {actuals.current_a:.0f} A, speed {actuals.speed_rpm:.0f} rpm)"
            )
        return (
            f"no actuals (TPDO1: torque, current, speed) from drive node {self.drive.node_id} for "
            f"{self._stale_s(actuals):.1f} s: nothing watches what the motor does"
        )


class InterlockMonitor:
    """Watches the interlocks from a thread of its own; keeps the first trip of the run in flight.

    on_trip(trip) is called (from the monitor or CAN thread) for every new trip while a run is armed,
    and for latched trips at any time; it must be quick and must not take the bench's run lock.
    stall_s: a gap this long between two monitor rounds means the process stalled: the drive has then
    missed our heartbeat for about that long, which trips the run in flight.
    """

    def __init__(
        self, interlocks: list[Interlock], on_trip: Callable[[Trip], None], period_s: float = 0.05, stall_s: float = 0.5
    ):
        self.interlocks = interlocks
        self.on_trip = on_trip
        self.period_s = period_s
        self.stall_s = stall_s
        self._lock = threading.Lock()
        self._armed = False
        self._run_trip: Trip | None = None
        self._last_trip: Trip | None = None
        self._reported: dict[str, str] = {}  # interlock -> reason already reported (no repeats while it holds)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle --------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="ripplecal-interlocks", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _loop(self) -> None:
        while True:
            slept_from = time.monotonic()
            if self._stop.wait(self.period_s):
                return
            # only the sleep is timed: a round's own slow reads (an SDO timeout) are not a stall
            overslept = time.monotonic() - slept_from - self.period_s
            with self._lock:
                armed = self._armed
            if armed and overslept > self.stall_s:
                self._tripped(
                    "service_stall",
                    f"heartbeat lost: the service stalled for {overslept:.1f} s (its heartbeat to the drive lapsed)",
                    latched=False,
                )
            try:
                self.check_now()
            except Exception:  # noqa: BLE001 - the watchdog must outlive any one bad reading
                log.exception("interlock monitor round failed")

    # --- runs ---------------------------------------------------------------------------------------
    def arm(self) -> None:
        with self._lock:
            self._armed = True
            self._run_trip = None
            for lock in self.interlocks:
                lock.armed_changed(True)
            # an armed-only interlock is not read between runs: a reason from the last run is stale
            for lock in self.interlocks:
                if lock.armed_only and not lock.latched:
                    lock.reason = None
                    self._reported.pop(lock.name, None)

    def check(self, interlock: "Interlock") -> Trip | None:
        """Read one interlock now (e.g. the supply before a point is committed: its monitor period may
        be longer than a point); returns the run's first trip."""
        reason = interlock.evaluate()
        if reason is not None:
            self._tripped(interlock.name, reason, interlock.latched)
        return self.run_trip

    def disarm(self) -> Trip | None:
        """End of a run: returns its first trip (None if it ran clean)."""
        with self._lock:
            self._armed = False
            for lock in self.interlocks:
                lock.armed_changed(False)
            trip, self._run_trip = self._run_trip, None
            return trip

    @property
    def run_trip(self) -> Trip | None:
        with self._lock:
            return self._run_trip

    # --- evaluation -----------------------------------------------------------------------------------
    def check_now(self, force: bool = False) -> Trip | None:
        """One round over every interlock that is due (all of them with force; callable from any
        thread, e.g. on a run's error path to learn whether an interlock is the first cause). Returns
        the run's first trip."""
        now = time.monotonic()
        with self._lock:
            armed = self._armed
        for lock in self.interlocks:
            if lock.armed_only and not armed:
                continue
            if not lock.due(now) and not force:
                if lock.reason is not None:
                    self._tripped(lock.name, lock.reason, lock.latched)
                continue
            reason = lock.evaluate()
            if reason is not None:
                self._tripped(lock.name, reason, lock.latched)
            else:
                with self._lock:
                    self._reported.pop(lock.name, None)
        return self.run_trip

    def pushed(self, interlock: Interlock, value: Any) -> None:
        """A value pushed to `interlock` (the drive's actuals, CAN receive thread): decided now, not at the
        next monitor round, so a trip takes the torque off within the push's period."""
        with self._lock:
            armed = self._armed
        if interlock.armed_only and not armed:
            return
        reason = interlock.decide(value)
        if reason is not None:
            self._tripped(interlock.name, reason, interlock.latched)

    def emcy(self, interlock: DeviceFault, code: int) -> None:
        """EMCY callback path (CAN receive thread)."""
        reason = interlock.on_emcy(code)
        if reason is not None:
            self._tripped(interlock.name, interlock.reason or reason, latched=True)

    def _tripped(self, name: str, reason: str, latched: bool) -> None:
        trip = Trip(
            name, reason, latched, datetime.now(timezone.utc).isoformat(timespec="milliseconds"), time.monotonic()
        )
        with self._lock:
            new_for_run = self._armed and self._run_trip is None
            if new_for_run:
                self._run_trip = trip
            same = self._reported.get(name) == reason
            if not same:
                self._reported[name] = reason
                self._last_trip = trip
        if new_for_run or not same:
            log.warning("interlock %s tripped: %s", name, reason)
            try:
                self.on_trip(trip)
            except Exception:  # noqa: BLE001 - reporting must not stop the watch
                log.exception("on_trip failed")

    # --- refusal and acknowledgement --------------------------------------------------------------------
    def refusal(self) -> Trip | None:
        """The interlock that forbids starting a run or commanding torque now (None: clear to go).
        Decided from a fresh reading of every interlock that is not armed-only."""
        now = time.monotonic()
        for lock in self.interlocks:
            if lock.armed_only:
                continue
            reason = lock.evaluate()
            if reason is not None:
                return Trip(
                    lock.name, reason, lock.latched, datetime.now(timezone.utc).isoformat(timespec="milliseconds"), now
                )
        return None

    def reset_latched(self) -> Trip | None:
        """After a person's fault reset: clear latched trips whose condition has gone; returns what
        still forbids a run (None: clear)."""
        for lock in self.interlocks:
            if lock.latched:
                lock.reset()
        with self._lock:
            self._last_trip = None
            self._reported.clear()
        return self.refusal()

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            run_trip, last = self._run_trip, self._last_trip
        return {
            "tripped": [
                {"interlock": lock.name, "reason": lock.reason, "latched": lock.latched}
                for lock in self.interlocks
                if lock.reason is not None
            ],
            "run_trip": run_trip.public() if run_trip else None,
            "last_trip": last.public() if last else None,
        }
