"""Interlocks: conditions under which no torque may flow, watched during every run (and between runs).

Modelled on bluesky's suspenders (bluesky/suspenders.py: SuspenderBase with `_should_suspend`,
`_should_resume`, `_get_justification`): each `Interlock` reads one signal of the bench, says whether
that value trips it and whether it has cleared, and justifies a trip in words an operator can act on
("EMCY 0x3210 DC link over-voltage", "heartbeat of drive node 5 lost", "DAQ ... disconnected").
Unlike a suspender, a trip never resumes a run by itself: the measurement in flight is discarded and a
sweep pauses; a *latched* interlock (drive FAULT/EMCY) also stays tripped until a person acknowledges
it (POST /bench/fault-reset), the others clear when their condition does.

The monitor that watches them, from its own thread, is service/bench/interlock_monitor.py; what a trip
records and the error a run stops with are service/bench/trips.py.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from typing import Any

from drivers.canopen_bus import CanBus
from drivers.cia402 import State402
from drivers.cia402_master import Cia402Master
from drivers.daq_reader import DaqReader
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveActuals, DriveClient
from drivers.emcy_codes import describe_emcy
from service.settings import SafetySettings

log = logging.getLogger(__name__)


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

    def __init__(self, device: Cia402Master):
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

    def __init__(self, device: Cia402Master):
        super().__init__()
        self.device = device
        self.name = f"{device.device_kind}_heartbeat"

    def read(self) -> tuple[bool, float | None]:
        return self.device.heartbeat_alive(), self.device.heartbeat_age_s()

    def should_trip(self, value: tuple[bool, float | None]) -> bool:
        return not value[0]

    def justification(self, value: tuple[bool, float | None]) -> str:
        age = value[1]
        seen = "never seen" if age is None else f"last seen {age:.1f} s ago"
        return f"heartbeat lost: {self.device.device_kind} node {self.device.node_id} ({seen})"


class ServiceHeartbeatStopped(Interlock):
    """Our own heartbeat is not being produced: the drive will fall to FAULT within its consumer time."""

    name = "service_heartbeat"

    def __init__(self, bus: CanBus):
        super().__init__()
        self.bus = bus

    def read(self) -> bool:
        return self.bus.heartbeat_producing()

    def should_trip(self, value: bool) -> bool:
        return not value

    def justification(self, value: bool) -> str:
        return f"heartbeat lost: the service's own heartbeat (node {self.bus.service_node_id}) is not being produced"


class DaqLost(Interlock):
    """The DAQ port is gone (unplugged, EOF/EIO), or a sample carries the sensor-fault flag."""

    name = "daq"

    def __init__(self, reader: DaqReader):
        super().__init__()
        self.reader = reader
        self._faults_seen: int | None = None

    def read(self) -> tuple[bool, int, str | None]:
        h = self.reader.health()
        return h["connected"], h.get("sensor_fault_samples", 0), h["last_error"]

    def should_trip(self, value: tuple[bool, int, str | None]) -> bool:
        connected, faults, _ = value
        new_faults = self._faults_seen is not None and faults > self._faults_seen
        self._faults_seen = faults
        self._new_faults = new_faults
        return not connected or new_faults

    def justification(self, value: tuple[bool, int, str | None]) -> str:
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

    def __init__(self, bus: CanBus):
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

    def __init__(self, supply: ScpiSupply, tolerance_fraction: float = 0.1, tolerance_v: float = 0.5):
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

    def should_trip(self, value: tuple[float, float] | None) -> bool:
        return value is not None and abs(value[0] - value[1]) > self.band(value[1])

    def should_clear(self, value: tuple[float, float] | None) -> bool:
        return value is None or abs(value[0] - value[1]) <= 0.5 * self.band(value[1])  # hysteresis

    def justification(self, value: tuple[float, float]) -> str:
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

    def __init__(self, drive: DriveClient, safety: SafetySettings, i_max_a: float, stale_s: float = 1.0):
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

    def read(self) -> DriveActuals | None:
        return self.drive.actuals

    def push(self, actuals: DriveActuals) -> None:
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

    def _stale_s(self, actuals: DriveActuals | None) -> float | None:
        if not self._watching:
            return None
        age = time.monotonic() - (self._since if actuals is None else max(actuals.received_at, self._since))
        return age if age > self.stale_s else None

    def _violation(self, actuals: DriveActuals | None) -> str | None:
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

    def should_trip(self, actuals: DriveActuals | None) -> bool:
        return self._violation(actuals) is not None or self._stale_s(actuals) is not None

    def justification(self, actuals: DriveActuals | None) -> str:
        violation = self._violation(actuals)
        if violation is not None and actuals is not None:  # a violation is always of actuals read
            return (
                f"the motor left the envelope: {violation} (drive node {self.drive.node_id}: torque "
                f"{actuals.torque_nm:.2f} Nm, current {actuals.current_a:.0f} A, speed {actuals.speed_rpm:.0f} rpm)"
            )
        return (
            f"no actuals (TPDO1: torque, current, speed) from drive node {self.drive.node_id} for "
            f"{self._stale_s(actuals):.1f} s: nothing watches what the motor does"
        )
