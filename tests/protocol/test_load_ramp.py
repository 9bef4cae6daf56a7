"""The load machine's ramp over CANopen (0x6083 profile acceleration, 0x6084 profile deceleration, rpm/s):
drivers.load_machine.LoadClient against the emulator's LoadMachineFirmware (a canopen LocalNode on a
python-can virtual bus, tests/support/drivers_peers.py), the firmware's setpoints driving the emulator's
own physics (paper-bench scenario, drive off: the load turns the shaft alone) a chunk at a time, as
plant_emulator/process.py does, so `velocity actual` (0x606C) read by SDO is the plant's after t
seconds of plant time.

Tolerances: the load's PI speed loop with acceleration feed-forward follows its ramped reference within
a few rpm (8 Hz loop on the shaft's inertia); 0x606C is an integer; 3 % of the ramped distance or 5 rpm,
whichever is wider, is several times both.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers import LOAD_EDS
from drivers.canopen_bus import CanBus
from drivers.cia402 import State402
from drivers.errors import SdoAbortError
from drivers.load_machine import LoadClient, LoadRamp
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.load_machine import LoadMachineFirmware
from tests.support.drivers_peers import EmulatedDevice, unique_channel

LOAD_NODE = 6
SERVICE_NODE = 1
CHUNK = 256
RAD_S_TO_RPM = 60.0 / (2.0 * math.pi)


class LoadOnPlant:
    """The emulated load machine on the emulator's physics: `run(seconds)` advances the plant a chunk
    at a time with the firmware's setpoints and publishes its speed and torque (read back by SDO)."""

    def __init__(self, channel: str):
        sc = scn.load("paper-bench")
        params, tab = scn.build(sc)
        params[ph.P_NOISE] = 0.0
        self.full_rpm_per_s = float(params[ph.P_LOAD_RAMP]) * RAD_S_TO_RPM
        self.peer = EmulatedDevice(
            LoadMachineFirmware, channel, LOAD_NODE, LOAD_EDS, ramp_rpm_per_s=self.full_rpm_per_s
        )
        self.plant = ph.Plant(params, tab, noise_seed=0, chunk=CHUNK)
        self.sp = ph.new_setpoints(12.0)  # drive off (S_POWER 0): only the load acts on the shaft
        self.sample_rate_hz = sc.sample_rate_hz

    @property
    def device(self) -> LoadMachineFirmware:
        device = self.peer.device
        assert isinstance(device, LoadMachineFirmware)
        return device

    def run(self, seconds: float) -> None:
        for _ in range(int(round(seconds * self.sample_rate_hz / CHUNK))):
            self.device.chunk_setpoints(self.sp)
            self.plant.run(self.sp, CHUNK, frames=False)
            speed_rpm = float(self.plant.x[ph.X_OMEGA_M]) * RAD_S_TO_RPM
            self.device.publish(speed_rpm, float(self.plant.summary[-1, ph.Y_LOAD_TORQUE_SUM]) / CHUNK)

    def close(self) -> None:
        self.peer.close()


@pytest.fixture
def channel() -> str:
    return unique_channel()


@pytest.fixture
def bench(channel):
    rig = LoadOnPlant(channel)
    yield rig
    rig.close()


@pytest.fixture
def load(channel, bench):
    with CanBus("virtual", channel, service_node_id=SERVICE_NODE, heartbeat_period_ms=50) as bus:
        client = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
        client.connect()
        yield client
        client.close()


def speed_tolerance_rpm(distance_rpm: float) -> float:
    return max(5.0, 0.03 * abs(distance_rpm))


def test_the_ramp_reads_back_and_starts_at_the_full_rate(load, bench):
    assert bench.full_rpm_per_s == pytest.approx(20000.0)  # paper-bench [load] ramp_rpm_per_s
    assert load.full_ramp_rpm_per_s == 20000
    assert load.read_ramp() == LoadRamp(20000, 20000, 20000)
    assert load.set_ramp_rpm_per_s(99.6) == 100
    assert bench.peer.writes_to(0x6083)[-1] == 100 and bench.peer.writes_to(0x6084)[-1] == 100
    assert load.read_ramp() == LoadRamp(100, 100, 20000)


@pytest.mark.parametrize("rate_rpm_per_s", [100.0, 1000.0])
def test_the_load_ramps_at_the_rate_set(load, bench, rate_rpm_per_s):
    """Speed actual after t s of plant time = rate * t, up and then down (deceleration at the same rate)."""
    load.set_ramp_rpm_per_s(rate_rpm_per_s)
    load.enable()
    load.set_speed_rpm(2600.0)
    elapsed_s = 0.0
    for t_s in (0.5, 1.0, 2.0):
        bench.run(t_s - elapsed_s)
        elapsed_s = t_s
        expected = min(rate_rpm_per_s * t_s, 2600.0)
        assert load.read_status().speed_rpm == pytest.approx(expected, abs=speed_tolerance_rpm(expected))
    top_rpm = min(rate_rpm_per_s * 2.0, 2600.0)
    load.set_speed_rpm(0.0)  # towards standstill: the deceleration, also slow
    bench.run(0.5)
    expected = top_rpm - 0.5 * rate_rpm_per_s
    assert load.read_status().speed_rpm == pytest.approx(expected, abs=speed_tolerance_rpm(0.5 * rate_rpm_per_s))
    load.brake_to_standstill()
    load.disable()


@pytest.mark.parametrize("bad", [0.0, -100.0, math.nan, math.inf, -math.inf, 0.4, 2.0**40])
def test_a_ramp_that_is_not_a_positive_finite_rate_is_refused_before_the_wire(load, bench, bad):
    with pytest.raises(ValueError, match="rpm/s"):
        load.set_ramp_rpm_per_s(bad)
    assert bench.peer.writes_to(0x6083) == [] and bench.peer.writes_to(0x6084) == []
    assert load.read_ramp() == LoadRamp(20000, 20000, 20000)


def test_the_load_refuses_a_ramp_above_its_full_rate(load, bench):
    with pytest.raises(SdoAbortError):
        load.set_ramp_rpm_per_s(20001.0)
    assert load.read_ramp() == LoadRamp(20000, 20000, 20000)


def _at_speed_on_a_slow_ramp(load: LoadClient, bench: LoadOnPlant, speed_rpm: float) -> None:
    """Up to speed at the full rate, then a run-up's slow ramp set."""
    load.enable()
    load.set_speed_rpm(speed_rpm)
    bench.run(0.5)
    assert load.read_status().speed_rpm == pytest.approx(speed_rpm, abs=5.0)
    load.set_ramp_rpm_per_s(100.0)


def test_a_plain_speed_0_keeps_the_slow_ramp(load, bench):
    """Why the stop needs brake_to_standstill: target 0 alone decelerates at 100 rpm/s."""
    _at_speed_on_a_slow_ramp(load, bench, 2000.0)
    load.set_speed_rpm(0.0)
    bench.run(0.5)
    assert load.read_status().speed_rpm == pytest.approx(1950.0, abs=5.0)


def test_brake_to_standstill_brakes_at_the_full_rate(load, bench):
    """2000 rpm at 20000 rpm/s: 0.1 s to the reference's standstill; 0.5 s of plant time is ample."""
    _at_speed_on_a_slow_ramp(load, bench, 2000.0)
    load.brake_to_standstill()
    assert load.read_ramp() == LoadRamp(20000, 20000, 20000)
    assert bench.peer.writes_to(0x60FF)[-1] == 0
    bench.run(0.5)
    assert abs(load.read_status().speed_rpm) <= 2.0
    assert load.state() is State402.OPERATION_ENABLED  # left enabled to brake; disabled at standstill
    load.disable()


def test_disable_restores_the_full_rate_for_the_next_run(load, bench):
    _at_speed_on_a_slow_ramp(load, bench, 1000.0)
    load.disable()
    assert load.read_ramp() == LoadRamp(20000, 20000, 20000)
    assert bench.device.state is State402.SWITCH_ON_DISABLED


def test_a_stop_without_a_slow_ramp_sends_nothing_more(load, bench):
    """No run-up, no extra SDO: the stop is what it was before ramps were settable."""
    load.enable()
    load.brake_to_standstill()
    load.disable()
    assert bench.peer.writes_to(0x6083) == [] and bench.peer.writes_to(0x6084) == []
    assert bench.peer.writes_to(0x60FF) == [0, 0]


def test_a_slow_ramp_left_in_force_is_restored_by_the_next_clients_first_stop(channel, bench):
    """A service that died mid run-up left 100 rpm/s in the load; the next one's connect reads it
    (writing nothing: the device is left as found) and its first stop restores the full rate."""
    with CanBus("virtual", channel, service_node_id=SERVICE_NODE, heartbeat_period_ms=50) as bus:
        first = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
        first.connect()
        first.set_ramp_rpm_per_s(100.0)
        first.close()
    with CanBus("virtual", channel, service_node_id=SERVICE_NODE, heartbeat_period_ms=50) as bus:
        successor = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
        successor.connect()
        try:
            assert bench.peer.writes_to(0x6083) == [100]
            successor.brake_to_standstill()
            assert successor.read_ramp() == LoadRamp(20000, 20000, 20000)
        finally:
            successor.close()


def test_the_fault_reaction_brakes_at_the_full_rate_whatever_the_ramp(load, bench):
    _at_speed_on_a_slow_ramp(load, bench, 2000.0)
    bench.device.heartbeat_lost()
    assert bench.device.state is State402.FAULT_REACTION_ACTIVE
    bench.run(0.5)
    assert bench.device.state is State402.FAULT
    assert np.isclose(bench.device.speed_rpm, 0.0, atol=2.0)
