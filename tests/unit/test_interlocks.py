"""The interlocks (service/bench/interlocks.py) and their monitor (service/bench/interlock_monitor.py)
on their own: each check against fake devices whose readings the test sets, the monitor's bookkeeping
(the run's first trip, reports without repeats, latching, refusal and reset) called directly, and its
thread on a clock the test steps. No bench, no emulator: the expectations are the rules the modules
state (bands, hysteresis, latching)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import pytest

from drivers.cia402 import State402
from service.bench import interlock_monitor
from service.bench.interlock_monitor import InterlockMonitor
from service.bench.interlocks import (
    DaqLost,
    DeviceFault,
    ForeignMaster,
    HeartbeatLost,
    Interlock,
    ServiceHeartbeatStopped,
    SupplyOutOfRange,
    daq_disconnected_reason,
)
from service.bench.trips import InterlockTripped, Trip
from tests.support.waiting import wait_until


# --- fakes: the readings a test sets ------------------------------------------------------------------
@dataclass
class FakeDevice:
    device_kind: str = "drive"
    node_id: int = 5
    current: State402 = State402.SWITCH_ON_DISABLED
    alive: bool = True
    age_s: float | None = 0.1

    def state(self) -> State402:
        return self.current

    def fault_description(self) -> str:
        return f"{self.device_kind} node {self.node_id} in FAULT"

    def heartbeat_alive(self) -> bool:
        return self.alive

    def heartbeat_age_s(self) -> float | None:
        return self.age_s


@dataclass
class FakeReader:
    url: str = "/dev/ripplecal-daq"
    connected: bool = True
    sensor_fault_samples: int = 0
    last_error: str | None = None

    def health(self) -> dict:
        return {
            "connected": self.connected,
            "sensor_fault_samples": self.sensor_fault_samples,
            "last_error": self.last_error,
        }


@dataclass
class FakeBus:
    producing: bool = True
    foreign: str | None = None
    service_node_id: int = 1

    def heartbeat_producing(self) -> bool:
        return self.producing

    def foreign_master(self) -> str | None:
        return self.foreign


@dataclass
class FakeSupply:
    measured_v: float = 12.0

    def measure_voltage(self) -> float:
        return self.measured_v


class Flag(Interlock):
    """The simplest interlock: trips while `value` is true; counts its reads; `broken` makes the read fail."""

    def __init__(self, name: str = "flag", latched: bool = False, armed_only: bool = False, period_s: float = 0.0):
        super().__init__()
        self.name, self.latched, self.armed_only, self.period_s = name, latched, armed_only, period_s
        self.value = False
        self.broken = False
        self.reads = 0

    def read(self) -> bool:
        self.reads += 1
        if self.broken:
            raise OSError("no answer")
        return self.value

    def should_trip(self, value: bool) -> bool:
        return value

    def justification(self, value: bool) -> str:
        return f"{self.name} raised"


@dataclass
class Reports:
    trips: list[Trip] = field(default_factory=list)

    def __call__(self, trip: Trip) -> None:
        self.trips.append(trip)

    @property
    def names(self) -> list[str]:
        return [t.interlock for t in self.trips]


class SteppedClock:
    """monotonic() for the monitor: each reading `step_s` later than the one before (thread safe)."""

    def __init__(self, step_s: float):
        self._lock = threading.Lock()
        self._t = 1000.0
        self.step_s = step_s

    def monotonic(self) -> float:
        with self._lock:
            self._t += self.step_s
            return self._t


# --- Trip and InterlockTripped ------------------------------------------------------------------------
def test_trip_public_leaves_out_the_monotonic_time():
    trip = Trip("daq", "DAQ gone", False, "2027-06-01T12:00:00.000+00:00", 123.4)
    assert trip.public() == {
        "interlock": "daq",
        "reason": "DAQ gone",
        "latched": False,
        "at": "2027-06-01T12:00:00.000+00:00",
    }


@pytest.mark.parametrize(
    "latched,refused,outcome,text",
    [
        (False, False, None, "interlock tripped: why"),
        (True, False, None, "interlock tripped: why"),
        (False, True, None, "refused: interlock tripped: why"),
        (True, True, None, "refused: interlock tripped: why; a person acknowledges it: POST /api/v1/bench/fault-reset"),
        (False, False, "make_safe failed: x", "interlock tripped: why; make_safe failed: x"),
    ],
)
def test_interlock_tripped_names_the_first_cause_and_how_to_clear_a_latched_refusal(latched, refused, outcome, text):
    trip = Trip("drive_fault", "why", latched, "t", 0.0)
    exc = InterlockTripped(trip, refused=refused, outcome=outcome)
    assert str(exc) == text
    assert exc.trip is trip and exc.refused is refused and exc.outcome == outcome


# --- Interlock: evaluate, latching, reset, due -----------------------------------------------------------
def test_a_trip_keeps_its_first_reason_and_a_plain_interlock_clears_with_its_condition():
    lock = Flag()
    assert lock.evaluate() is None
    lock.value = True
    assert lock.evaluate() == "flag raised"
    lock.justification = lambda value: "a later reason"  # the first cause is kept while it holds
    assert lock.evaluate() == "flag raised"
    lock.value = False
    assert lock.evaluate() is None and lock.reason is None


def test_a_latched_trip_holds_until_reset_and_reset_keeps_it_while_the_condition_holds():
    lock = Flag(latched=True)
    lock.value = True
    assert lock.evaluate() == "flag raised"
    lock.value = False
    assert lock.evaluate() == "flag raised"  # gone, but latched: a person acknowledges it
    lock.value = True
    assert lock.reset() == "flag raised"  # acknowledged while still there: tripped again
    lock.value = False
    assert lock.reset() is None and lock.evaluate() is None


def test_an_unreadable_signal_decides_nothing():
    lock = Flag()
    lock.broken = True
    assert lock.evaluate() is None  # not tripped by a failed read
    lock.broken, lock.value = False, True
    lock.evaluate()
    lock.broken, lock.value = True, False
    assert lock.evaluate() == "flag raised"  # nor cleared by one


def test_due_spaces_the_reads_by_the_period():
    lock = Flag(period_s=0.25)
    assert [lock.due(t) for t in (10.0, 10.1, 10.24, 10.25, 10.3, 10.5)] == [True, False, False, True, False, True]


# --- the checks ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("state,trips", [(s, s in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)) for s in State402])
def test_device_fault_trips_in_fault_and_fault_reaction_only(state, trips):
    device = FakeDevice(current=state)
    lock = DeviceFault(device)
    assert lock.name == "drive_fault" and lock.latched
    assert (lock.evaluate() == "drive node 5 in FAULT") is trips
    assert (lock.reason is not None) is trips


def test_device_fault_emcy_trips_latched_except_an_error_reset():
    lock = DeviceFault(FakeDevice(device_kind="load", node_id=6))
    assert lock.on_emcy(0x0000) is None and lock.on_emcy(0x0001) is None  # error reset / no error: high byte 0
    assert lock.reason is None
    reason = lock.on_emcy(0x3210)
    assert reason == "EMCY 0x3210 DC link over-voltage from load node 6" and lock.reason == reason
    assert lock.on_emcy(0x8130).startswith("EMCY 0x8130") and lock.reason == reason  # the first cause is kept
    assert lock.evaluate() == reason  # the device reads fine again: still latched
    assert lock.reset() is None


@pytest.mark.parametrize("age_s,seen", [(None, "never seen"), (1.24, "last seen 1.2 s ago")])
def test_heartbeat_lost_names_the_device_and_when_it_was_last_seen(age_s, seen):
    device = FakeDevice(device_kind="load", node_id=6, alive=False, age_s=age_s)
    lock = HeartbeatLost(device)
    assert lock.name == "load_heartbeat" and not lock.latched
    assert lock.evaluate() == f"heartbeat lost: load node 6 ({seen})"
    device.alive = True
    assert lock.evaluate() is None


def test_service_heartbeat_stopped():
    bus = FakeBus(producing=False, service_node_id=3)
    lock = ServiceHeartbeatStopped(bus)
    assert lock.evaluate() == "heartbeat lost: the service's own heartbeat (node 3) is not being produced"
    bus.producing = True
    assert lock.evaluate() is None


def test_daq_lost_on_disconnect_names_the_port_and_the_error():
    reader = FakeReader()
    lock = DaqLost(reader)
    assert lock.evaluate() is None
    reader.connected, reader.last_error = False, "EIO"
    assert lock.evaluate() == "DAQ /dev/ripplecal-daq disconnected (EIO)" == daq_disconnected_reason(reader.url, "EIO")
    reader.connected = True
    assert lock.evaluate() is None


def test_daq_lost_trips_on_new_sensor_fault_samples_only():
    reader = FakeReader(sensor_fault_samples=7)  # counted before we watched: a baseline, not a trip
    lock = DaqLost(reader)
    assert lock.evaluate() is None
    assert lock.evaluate() is None  # no new ones
    reader.sensor_fault_samples = 9
    assert lock.evaluate() == "DAQ /dev/ripplecal-daq: sensor fault flag set"
    assert lock.evaluate() is None  # the count stands still: cleared (not latched)


def test_foreign_master_trips_while_one_is_heard():
    bus = FakeBus(foreign="heartbeat of node 1 from another host")
    lock = ForeignMaster(bus)
    assert lock.evaluate() == (
        "a second master on the bus: heartbeat of node 1 from another host; stop it (one service per bench)"
    )
    bus.foreign = None
    assert lock.evaluate() is None


@pytest.mark.parametrize("expected_v,band_v", [(12.0, 1.2), (48.0, 4.8), (3.0, 0.5), (-12.0, 1.2), (0.0, 0.5)])
def test_supply_band_is_ten_percent_but_at_least_half_a_volt(expected_v, band_v):
    assert SupplyOutOfRange(FakeSupply()).band(expected_v) == pytest.approx(band_v)


def test_supply_out_of_range_trips_outside_the_band_and_clears_inside_half_of_it():
    supply = FakeSupply()
    lock = SupplyOutOfRange(supply)
    assert lock.armed_only and not lock.latched
    supply.measured_v = 0.0
    assert lock.evaluate() is None  # no voltage set (between runs): nothing to watch
    lock.expected_v = 12.0
    supply.measured_v = 13.1  # 1.1 V off, band 1.2 V
    assert lock.evaluate() is None
    supply.measured_v = 10.7  # 1.3 V off
    assert lock.evaluate() == "DC supply out of range: measures 10.70 V, set 12.00 V (band +-1.20 V)"
    supply.measured_v = 11.3  # back inside the band, not inside half of it (0.6 V)
    assert lock.evaluate() is not None
    supply.measured_v = 11.5
    assert lock.evaluate() is None
    supply.measured_v = 10.0
    assert lock.evaluate() is not None
    lock.expected_v = None  # the run ended: clears
    assert lock.evaluate() is None


# --- the monitor ---------------------------------------------------------------------------------------------
def test_the_first_trip_of_an_armed_run_is_kept_and_every_new_one_is_reported():
    a, b = Flag("a"), Flag("b")
    reports = Reports()
    monitor = InterlockMonitor([a, b], reports)
    monitor.arm()
    assert monitor.check_now() is None and reports.trips == []
    a.value = True
    first = monitor.check_now()
    assert (first.interlock, first.reason, first.latched) == ("a", "a raised", False)
    b.value = True
    assert monitor.check_now() == first  # the run's first cause stays the first
    assert reports.names == ["a", "b"]
    monitor.check_now()
    assert reports.names == ["a", "b"]  # no repeats while they hold
    assert monitor.disarm() == first
    assert monitor.run_trip is None and monitor.disarm() is None


def test_a_trip_that_clears_and_comes_again_is_reported_again():
    a = Flag("a")
    reports = Reports()
    monitor = InterlockMonitor([a], reports)
    a.value = True
    monitor.check_now()
    a.value = False
    monitor.check_now()
    a.value = True
    monitor.check_now()
    assert reports.names == ["a", "a"]
    assert monitor.run_trip is None  # not armed: no run to stop


def test_a_new_run_is_told_of_a_trip_that_still_holds():
    a = Flag("a", latched=True)
    reports = Reports()
    monitor = InterlockMonitor([a], reports)
    a.value = True
    monitor.check_now()
    monitor.arm()
    trip = monitor.check_now()
    assert trip is not None and trip.interlock == "a" and trip.latched
    assert reports.names == ["a", "a"]  # the same reason, but new for this run


def test_armed_only_interlocks_are_read_during_runs_only_and_their_old_reasons_go_at_arm():
    supply_like = Flag("supply", armed_only=True)
    monitor = InterlockMonitor([supply_like], Reports())
    supply_like.value = True
    assert monitor.check_now() is None and supply_like.reads == 0
    assert monitor.refusal() is None  # never refuses a run: it has no reading between runs
    monitor.arm()
    assert monitor.check_now().interlock == "supply"
    monitor.disarm()
    supply_like.value = False
    monitor.arm()
    assert supply_like.reason is None  # the last run's reason is stale: gone at arm
    assert monitor.check_now() is None


def test_a_read_waits_for_its_period_unless_forced_and_a_held_reason_is_still_reported(monkeypatch):
    monkeypatch.setattr(interlock_monitor, "time", SteppedClock(0.01))  # 10 ms per reading of the clock
    slow = Flag("slow", period_s=10.0)
    monitor = InterlockMonitor([slow], Reports())
    monitor.check_now()
    assert slow.reads == 1
    monitor.check_now()
    assert slow.reads == 1  # not due again for 10 s
    slow.value = True
    monitor.check_now(force=True)
    assert slow.reads == 2 and slow.reason == "slow raised"
    monitor.arm()
    trip = monitor.check_now()  # not due: the reason it holds trips the run
    assert slow.reads == 2 and trip is not None and trip.interlock == "slow"


def test_check_reads_one_interlock_now():
    a, b = Flag("a", period_s=60.0), Flag("b")
    monitor = InterlockMonitor([a, b], Reports())
    monitor.arm()
    a.value = True
    assert monitor.check(a).interlock == "a" and b.reads == 0


def test_emcy_trips_latched_at_once_from_the_can_thread():
    device = FakeDevice()
    fault = DeviceFault(device)
    reports = Reports()
    monitor = InterlockMonitor([fault], reports)
    monitor.emcy(fault, 0x0000)
    assert reports.trips == []
    monitor.arm()
    monitor.emcy(fault, 0x3210)
    trip = monitor.run_trip
    assert trip.interlock == "drive_fault" and trip.latched
    assert trip.reason == "EMCY 0x3210 DC link over-voltage from drive node 5"
    assert reports.trips == [trip]
    assert monitor.refusal().reason == trip.reason  # latched: refuses the next run until reset
    assert monitor.reset_latched() is None  # the device is not in FAULT: the reset clears it
    assert monitor.snapshot()["tripped"] == []


def test_refusal_names_the_first_interlock_tripped_now():
    a, b, c = Flag("a"), Flag("b"), Flag("c", armed_only=True)
    monitor = InterlockMonitor([a, b, c], Reports())
    assert monitor.refusal() is None
    b.value = c.value = True
    refusal = monitor.refusal()
    assert (refusal.interlock, refusal.reason, refusal.latched) == ("b", "b raised", False)
    a.value = True
    assert monitor.refusal().interlock == "a"


def test_reset_latched_clears_what_has_gone_and_returns_what_still_forbids_a_run():
    device = FakeDevice(current=State402.FAULT)
    fault, other = DeviceFault(device), Flag("other", latched=True)
    reports = Reports()
    monitor = InterlockMonitor([fault, other], reports)
    other.value = True
    monitor.check_now()
    other.value = False
    assert monitor.snapshot()["last_trip"] is not None
    still = monitor.reset_latched()
    assert still.interlock == "drive_fault" and still.reason == "drive node 5 in FAULT"  # the drive is still in FAULT
    assert other.reason is None
    device.current = State402.SWITCH_ON_DISABLED
    assert monitor.reset_latched() is None
    assert monitor.snapshot() == {"tripped": [], "run_trip": None, "last_trip": None}


def test_snapshot_shows_what_is_tripped_the_run_trip_and_the_last_trip():
    a, b = Flag("a", latched=True), Flag("b")
    monitor = InterlockMonitor([a, b], Reports())
    monitor.arm()
    a.value = True
    monitor.check_now()
    b.value = True
    monitor.check_now()
    snap = monitor.snapshot()
    assert snap["tripped"] == [
        {"interlock": "a", "reason": "a raised", "latched": True},
        {"interlock": "b", "reason": "b raised", "latched": False},
    ]
    assert snap["run_trip"]["interlock"] == "a" and "monotonic" not in snap["run_trip"]
    assert snap["last_trip"]["interlock"] == "b"


def test_a_failing_on_trip_does_not_stop_the_watch():
    def on_trip(trip):
        raise RuntimeError("the reporter broke")

    a = Flag("a")
    monitor = InterlockMonitor([a], on_trip)
    monitor.arm()
    a.value = True
    assert monitor.check_now().interlock == "a"


# --- the monitor's thread --------------------------------------------------------------------------------------
def test_the_thread_reports_a_trip_without_being_asked():
    a = Flag("a")
    reports = Reports()
    monitor = InterlockMonitor([a], reports, period_s=0.01)
    monitor.start()
    try:
        a.value = True
        wait_until(lambda: reports.trips, 10, "the trip reported by the monitor's thread")
    finally:
        monitor.stop()
    assert reports.names == ["a"]


@pytest.mark.parametrize("armed", [True, False])
def test_a_stall_between_rounds_trips_an_armed_run(monkeypatch, armed):
    """Each clock reading 1 s after the last: every sleep of 10 ms looks overslept by about 1 s, more than
    stall_s, which is what a stopped process sees when it runs again."""
    monkeypatch.setattr(interlock_monitor, "time", SteppedClock(1.0))
    reports = Reports()
    probe = Flag("probe")  # read once a round: rounds are known to have run
    monitor = InterlockMonitor([probe], reports, period_s=0.01, stall_s=0.5)
    if armed:
        monitor.arm()
    monitor.start()
    try:
        wait_until(lambda: probe.reads >= 3, 10, "three monitor rounds")
    finally:
        monitor.stop()
    if armed:
        trip = monitor.run_trip
        assert trip.interlock == "service_stall" and not trip.latched
        assert trip.reason.startswith("heartbeat lost: the service stalled for ")
        assert "its heartbeat to the drive lapsed" in trip.reason
    else:
        assert reports.trips == [] and monitor.run_trip is None
