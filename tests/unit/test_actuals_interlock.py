"""The actuals interlock (service/bench/interlocks.py ActualsOutsideLimits) on its own: the drive's actuals as
its TPDO delivers them, pushed through the monitor as the CAN receive thread does, against the limits of the
settings. No bench, no emulator (tests/e2e/test_envelope_e2e.py runs it on the emulated bench)."""

from __future__ import annotations

import time

import pytest

from drivers.drive import DriveActuals
from service.bench.interlock_monitor import InterlockMonitor
from service.bench.interlocks import ActualsOutsideLimits
from service.settings import load_settings


class FakeDrive:
    node_id = 5

    def __init__(self):
        self.actuals: DriveActuals | None = None


def actuals(torque_nm=2.5, speed_rpm=2000.0, current_a=60.0, age_s=0.0) -> DriveActuals:
    return DriveActuals(torque_nm, speed_rpm, current_a, time.monotonic() - age_s)


def watch(**safety) -> tuple[FakeDrive, ActualsOutsideLimits, InterlockMonitor, list]:
    settings = load_settings(environ={}, overrides={f"safety.{k}": v for k, v in safety.items()})
    drive = FakeDrive()
    lock = ActualsOutsideLimits(drive, settings.safety, settings.motor.i_max_a)
    trips: list = []
    return drive, lock, InterlockMonitor([lock], trips.append), trips


def push(drive, lock, monitor, value) -> None:
    """What BenchFaults does on every TPDO: the latest kept, the mean fed, the value decided at once."""
    drive.actuals = value
    lock.push(value)
    monitor.pushed(lock, value)


@pytest.mark.parametrize(
    "value, why",
    [
        (actuals(current_a=218.0), "current actual 218.0 A above 1.25 x motor.i_max_a = 141.2 A"),
        (actuals(torque_nm=-5.69, current_a=100.0), "torque actual -5.69 Nm beyond the limit of 5 Nm"),
        (actuals(speed_rpm=6700.0), "speed actual 6700 rpm beyond the limit of 6000 rpm"),
    ],
)
def test_an_actual_beyond_a_limit_trips_the_run_at_once_and_latches(value, why):
    drive, lock, monitor, trips = watch()
    monitor.arm()
    push(drive, lock, monitor, actuals())
    assert monitor.run_trip is None and trips == []
    push(drive, lock, monitor, value)
    trip = monitor.run_trip
    assert trip is not None and trip.interlock == "actuals" and trip.latched and why in trip.reason
    assert "the motor left the envelope" in trip.reason and len(trips) == 1
    push(drive, lock, monitor, actuals())  # back within the limits: still tripped until a person resets
    assert monitor.disarm() is trip and monitor.refusal() is not None
    assert monitor.reset_latched() is None  # the condition has gone


def test_within_the_margins_nothing_trips():
    drive, lock, monitor, trips = watch()
    monitor.arm()
    for value in (actuals(torque_nm=5.4, current_a=140.0), actuals(torque_nm=-5.4, speed_rpm=6590.0)):
        push(drive, lock, monitor, value)
    assert monitor.run_trip is None and trips == []


def test_the_torque_sign_of_the_bench_is_held_on_the_actual():
    drive, lock, monitor, _ = watch(torque_sign="positive", max_torque_nm=3.0)
    monitor.arm()
    push(drive, lock, monitor, actuals(torque_nm=-0.2))  # within 10 % of 3 Nm: the estimate's offset
    assert monitor.run_trip is None
    push(drive, lock, monitor, actuals(torque_nm=-0.85, current_a=118.0))
    assert "torque actual -0.85 Nm: this bench allows positive torque only" in monitor.run_trip.reason


def test_actuals_that_stop_during_a_run_trip_it_but_not_between_runs():
    drive, lock, monitor, _ = watch()
    drive.actuals = actuals(age_s=5.0)
    assert lock.evaluate() is None  # between runs: nothing runs, nothing to watch
    monitor.arm()
    lock._since -= 2.0  # the run started 2 s ago and no TPDO came since
    monitor.check_now(force=True)
    assert "no actuals (TPDO1: torque, current, speed) from drive node 5" in monitor.run_trip.reason


def test_the_mean_torque_is_over_what_arrived_since_it_started():
    drive, lock, monitor, _ = watch()
    monitor.arm()
    push(drive, lock, monitor, actuals(torque_nm=4.5))  # before the measurement: not counted
    lock.start_mean()
    assert lock.mean_torque() == (None, 0)
    for t in (2.4, 2.5, 2.6):
        push(drive, lock, monitor, actuals(torque_nm=t))
    mean, count = lock.mean_torque()
    assert count == 3 and mean == pytest.approx(2.5)
