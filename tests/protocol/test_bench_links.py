"""BenchLinks.open arms the heartbeat consumers only once the bench is whole, and leaves the devices as
found when it is not (issue 25, finding 5); no mocks.

The peers are the emulator's own CiA 402 devices on a python-can virtual bus (tests/support/
drivers_peers.py), a SCPI supply on a loopback socket and a real pty the DAQ frames are written into at
16 kHz on the wall clock. Both devices come up consuming node 1's heartbeat at 500 ms, as their EDS
stores it (a device that watches the service from power-up): such a device faults once it has heard
the heartbeat and it stops, so the service must not send one before it stays.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from drivers import DRIVE_EDS, LOAD_EDS
from drivers.daq_protocol import FRAME_BYTES, encode_frames
from plant_emulator.drive_firmware import DriveFirmware
from plant_emulator.load_machine import LoadMachineFirmware
from service.bench.connections import LEFT_AS_FOUND, BenchLinks
from service.bench.errors import BenchUnreachable
from service.settings import Settings
from tests.support.drivers_peers import EmulatedDevice, ScpiPeer, unique_channel
from tests.support.pty_writer import PtyWriter

DRIVE_NODE, LOAD_NODE, SERVICE_NODE = 5, 6, 1
RATE_HZ = 16_000
ARMED = (SERVICE_NODE << 16) | 500  # 0x1016:1 as the EDS stores it and as the service arms it
OD_CONSUMER = (0x1016, 1)
HEARTBEAT_HOLD_S = 1.5  # three consumer times: a device that heard the heartbeat and lost it has faulted


@pytest.fixture
def bench():
    channel = unique_channel()
    drive = EmulatedDevice(DriveFirmware, channel, DRIVE_NODE, DRIVE_EDS)
    load = EmulatedDevice(LoadMachineFirmware, channel, LOAD_NODE, LOAD_EDS, ramp_rpm_per_s=20000.0)
    supply = ScpiPeer()
    daq = PtyWriter()
    n = 10 * RATE_HZ  # more than any open() below reads
    zeros = np.zeros(n, dtype=np.int64)
    daq.write_at_rate(encode_frames(np.arange(n), zeros, zeros, zeros), 32 * FRAME_BYTES, RATE_HZ * FRAME_BYTES)
    settings = Settings(
        bench_mode="bench",
        can={"interface": "virtual", "channel": channel, "host": None, "heartbeat_period_ms": 50},
        daq={"url": daq.path, "sample_rate_hz": RATE_HZ, "read_timeout_s": 2.0},
        supply={"url": supply.url},
    )
    yield settings, drive, load, daq
    for part in (drive, load, supply, daq):
        part.close()


def _not_faulted_after_the_hold(*peers: EmulatedDevice) -> None:
    time.sleep(HEARTBEAT_HOLD_S)
    for peer in peers:
        peer.device.check_heartbeat()  # what the emulator's watchdog does every 20 ms
        assert peer.device.state.value != "fault", peer.device.state


def test_a_whole_bench_arms_both_consumers_and_an_orderly_close_disarms_them(bench):
    settings, drive, load, _ = bench
    links = BenchLinks(settings)
    links.open()
    try:
        assert drive.device.heartbeat_consumer_ms == 500 and load.device.heartbeat_consumer_ms == 500
        assert links.bus.heartbeat_producing()
    finally:
        links.close()
    assert drive.writes_to(*OD_CONSUMER) == [ARMED, 0] and load.writes_to(*OD_CONSUMER) == [ARMED, 0]
    _not_faulted_after_the_hold(drive, load)


def test_a_consumer_that_cannot_be_armed_leaves_the_other_as_found(bench):
    settings, drive, load, _ = bench

    def refuse_consumer(index, subindex, od, data, **_kwargs):
        if (index, subindex) == OD_CONSUMER:
            raise SdoAbortedError(0x08000022)  # "because of the present device state"

    load.node._write_callbacks.insert(0, refuse_consumer)
    links = BenchLinks(settings)
    with pytest.raises(BenchUnreachable) as info:
        links.open()
    message = str(info.value)
    assert "drive and load heartbeat consumers" in message and "0x1016:01" in message, message
    assert message.endswith(LEFT_AS_FOUND), message
    # the drive was armed, then written back as found; no heartbeat was ever sent for it to miss
    assert drive.writes_to(*OD_CONSUMER) == [ARMED, ARMED] and load.writes_to(*OD_CONSUMER) == []  # refused
    assert drive.device._hb_last is None and load.device._hb_last is None
    _not_faulted_after_the_hold(drive, load)


def test_a_bench_that_is_not_whole_writes_no_consumer_and_sends_no_heartbeat(bench):
    settings, drive, load, _ = bench
    silent = PtyWriter()  # a port that opens but streams nothing: the last link fails
    try:
        settings = settings.model_copy(update={"daq": settings.daq.model_copy(update={"url": silent.path})})
        links = BenchLinks(settings)
        with pytest.raises(BenchUnreachable, match=f"DAQ at .*DaqNotStreaming.*; {LEFT_AS_FOUND}$"):
            links.open()
    finally:
        silent.close()
    assert drive.writes_to(*OD_CONSUMER) == [] and load.writes_to(*OD_CONSUMER) == []
    assert drive.device._hb_last is None and load.device._hb_last is None  # never heard the service
    _not_faulted_after_the_hold(drive, load)
