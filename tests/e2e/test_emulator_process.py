"""`python -m plant_emulator` as a process, through its real wires: socketcand + canopen, DAQ pty,
SCPI over TCP. Tests run in file order on one emulator; the last one stops it with SIGTERM (the two
that need a DAQ nobody reads have an emulator of their own)."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import canopen
import numpy as np
import pytest
import serial

from drivers import DRIVE_EDS, LOAD_EDS
from drivers.canopen_bus import CanBus
from drivers.cia402 import CONTROLWORD, PATH_TO_OPERATION_ENABLED, State402, decode_statusword
from drivers.daq_protocol import FLAG_SYNC_INPUT, FrameDecoder
from drivers.daq_reader import DaqReader
from drivers.load_machine import LoadClient
from tests.support.bench_rig import EmulatorRig, emulator_control
from tests.support.parent_death import die_with_parent
from tests.support.waiting import wait_until

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def emulator():
    proc = subprocess.Popen(
        [sys.executable, "-m", "plant_emulator", "--speedup", "0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        preexec_fn=die_with_parent(signal.SIGTERM),  # ends with pytest, even killed
    )
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 60.0)
        assert ready, "emulator printed no endpoints within 60 s"
        endpoints = json.loads(proc.stdout.readline())
        yield proc, endpoints
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()


@pytest.fixture(scope="module")
def bench(emulator):
    proc, ep = emulator
    net = canopen.Network()
    net.connect(interface="socketcand", host=ep["can"]["host"], port=ep["can"]["port"], channel=ep["can"]["channel"])
    heartbeat = net.send_periodic(0x701, [0x05], 0.1)
    drive = canopen.RemoteNode(ep["drive_node"], str(DRIVE_EDS))
    load = canopen.RemoteNode(ep["load_node"], str(LOAD_EDS))
    net.add_node(drive)
    net.add_node(load)
    daq = serial.Serial(ep["daq"], timeout=0.5)
    state = {"net": net, "heartbeat": heartbeat, "drive": drive, "load": load, "daq": daq, "decoder": FrameDecoder()}
    try:
        yield state
    finally:
        daq.close()
        try:
            state["heartbeat"].stop()
        except Exception:
            pass
        net.disconnect()


def read_samples(bench, n: int):
    """Next n decoded samples from the DAQ (--speedup 0: the plant runs as fast as we read; unread, in real time)."""
    parts, got = [], 0
    deadline = time.monotonic() + 20.0
    while got < n and time.monotonic() < deadline:
        s = bench["decoder"].feed(bench["daq"].read(min(65536, 12 * (n - got) + 12)))
        if len(s):
            parts.append(s)
            got += len(s)
    assert got >= n, f"only {got} of {n} samples within 20 s"
    bench["sync_level"] = int(parts[-1].flags[-1] & FLAG_SYNC_INPUT)
    return (
        np.concatenate([p.index for p in parts]),
        np.concatenate([p.angle_rad for p in parts]),
        np.concatenate([p.accel_fs for p in parts]),
        np.concatenate([p.flags for p in parts]),
    )


def toggles_after(bench, n: int) -> int:
    """Number of sync-flag toggles in the next n samples, counted from the last level seen."""
    before = bench.get("sync_level", 0)
    flags = read_samples(bench, n)[3]
    sync = (flags & FLAG_SYNC_INPUT).astype(int)
    return int(np.count_nonzero(np.diff(np.concatenate([[before], sync]))))


def state_of(node) -> State402:
    return decode_statusword(node.sdo[0x6041].raw)


def enable(node) -> None:
    for _ in range(8):
        s = state_of(node)
        if s == State402.OPERATION_ENABLED:
            return
        node.sdo[0x6040].raw = CONTROLWORD[PATH_TO_OPERATION_ENABLED[s]]
    assert state_of(node) == State402.OPERATION_ENABLED


def test_first_line_names_the_endpoints(emulator):
    _, ep = emulator
    assert ep["can"]["interface"] == "socketcand" and ep["can"]["host"] == "127.0.0.1"
    assert ep["can"]["channel"] == "can0" and ep["can"]["port"] > 0
    # a stable path (symlink, like /dev/serial/by-id/...) to the pty the DAQ is
    assert os.path.islink(ep["daq"]) and os.path.realpath(ep["daq"]) == ep["daq_device"]
    assert ep["daq_device"].startswith("/dev/")
    assert ep["supply"].startswith("socket://127.0.0.1:")
    assert (ep["drive_node"], ep["load_node"], ep["sample_rate_hz"]) == (5, 6, 16000)
    assert ep["scenario"] == "paper-bench" and ep["seed"] is None


def test_sdo_identity_and_statusword(bench):
    drive = bench["drive"]
    assert drive.sdo[0x1018][1].raw == 0x0EAC
    assert drive.sdo[0x6076].raw == 5000
    assert state_of(drive) == State402.SWITCH_ON_DISABLED


def test_supply_over_scpi(emulator):
    _, ep = emulator
    port = serial.serial_for_url(ep["supply"], timeout=2.0)
    try:
        port.write(b"*IDN?\n")
        assert port.readline().decode().strip() == "ripplecal,emulated-supply,0,0.1"
        port.write(b"OUTP?\n")
        assert port.readline().strip() == b"0"  # starts OFF
        port.write(b"VOLT 12\nOUTP ON\nVOLT?\n")
        assert float(port.readline()) == pytest.approx(12.0)
        port.write(b"MEAS:VOLT?\n")
        assert float(port.readline()) == pytest.approx(12.0, abs=0.01)
        port.write(b"VOLT 99\nSYST:ERR?\n")  # out of range: queued error
        assert port.readline().startswith(b"-222")
    finally:
        port.close()


def test_daq_frames_decode(bench):
    index, angle, accel, flags = read_samples(bench, 8000)
    assert np.all(np.diff(index) == 1)
    c = bench["decoder"].counters
    assert c.crc_failures == 0 and c.sequence_gaps == 0
    assert np.all((angle >= 0) & (angle < 2 * np.pi))
    assert np.all(np.abs(accel) <= 1.0)


def test_enable_torque_and_sync_toggle(bench):
    drive, load = bench["drive"], bench["load"]
    enable(load)
    load.sdo[0x60FF].raw = 2000
    enable(drive)
    assert drive.sdo[0x6061].raw == 4
    read_samples(bench, 4096)
    drive.sdo[0x6071].raw = 500  # 2.5 Nm
    assert toggles_after(bench, 16000 * 3) == 1, "one setpoint, one toggle"
    with pytest.raises(canopen.SdoAbortedError) as exc:
        drive.sdo[0x6071].raw = 1500
    assert exc.value.code == 0x06090030
    assert drive.sdo[0x606C].raw == pytest.approx(2000, abs=20)
    assert drive.sdo[0x6077].raw == pytest.approx(500, abs=10)
    assert drive.sdo[0x6079].raw == pytest.approx(12000, abs=10)
    # R i_q + w_e psi(|i|) at OP1 (saturated psi: 6.43 V) plus the PI's answer to the dead-time voltage
    # (fundamental 4/pi U_dc T_dead f_pwm = 0.24 V against the current)
    assert drive.sdo[0x2010][2].raw == pytest.approx(6.67, abs=0.1)


def test_injection_commit_is_one_toggle(bench):
    drive = bench["drive"]
    count = drive.sdo[0x2000][7].raw
    drive.sdo[0x2000][3].raw = 0.009
    drive.sdo[0x2000][4].raw = 0.0516
    drive.sdo[0x2000][7].raw = 1
    assert drive.sdo[0x2000][7].raw == (count + 1) % 256
    assert toggles_after(bench, 16000 * 3) == 1
    drive.sdo[0x2000][2].raw = 1  # mode manual: one more
    assert toggles_after(bench, 16000 * 3) == 1


def test_heartbeat_loss_faults_the_drive(bench):
    drive = bench["drive"]
    emcy = []
    drive.emcy.add_callback(emcy.append)
    bench["heartbeat"].stop()
    assert wait_until(lambda: state_of(drive) == State402.FAULT, 10.0)  # consumer time 500 ms
    assert drive.sdo[0x6071].raw == 0 and drive.sdo[0x2000][2].raw == 0
    assert any(e.code == 0x8130 for e in emcy)
    bench["heartbeat"] = bench["net"].send_periodic(0x701, [0x05], 0.1)
    time.sleep(0.2)
    drive.sdo[0x6040].raw = CONTROLWORD[PATH_TO_OPERATION_ENABLED[State402.FAULT]]
    assert state_of(drive) == State402.SWITCH_ON_DISABLED


def test_lut_download_over_sdo_segmented(bench):
    import zlib

    from drivers import lut_image

    drive = bench["drive"]
    good = lut_image.encode(6, [1.0, 2.5, 4.0], [1000.0, 2000.0], [12.0], np.full(6, 0.01), np.full(6, -0.02), map_id=5)
    drive.sdo.download(0x2001, 1, good, force_segment=True)
    assert drive.sdo[0x2001][2].raw == zlib.crc32(good[:-4])
    assert drive.sdo[0x2001][3].raw == 1 and drive.sdo[0x2001][4].raw == 5
    with pytest.raises(canopen.SdoAbortedError) as exc:
        drive.sdo.download(0x2001, 1, good[:-1] + bytes([good[-1] ^ 0xFF]), force_segment=True)
    assert exc.value.code == 0x08000020
    assert drive.sdo[0x2001][2].raw == zlib.crc32(good[:-4])
    assert drive.sdo[0x2001][3].raw == 2 and drive.sdo[0x2001][4].raw == 5


def test_control_socket_faults(emulator, bench):
    _, ep = emulator
    assert ep["control"].startswith("tcp://127.0.0.1:")  # test-only: on loopback
    drive = bench["drive"]
    assert emulator_control(ep, {"fault": "nonsense"})["ok"] is False
    # frames already produced (queue + pty buffer, < 32k samples) pass unharmed
    before = bench["decoder"].counters.crc_failures
    assert emulator_control(ep, {"fault": "daq_corrupt", "rate": 0.01})["ok"] is True
    read_samples(bench, 48000)
    assert bench["decoder"].counters.crc_failures > before
    assert emulator_control(ep, {"fault": "clear"})["ok"] is True
    read_samples(bench, 40000)  # flush what was corrupted
    before = bench["decoder"].counters.crc_failures
    read_samples(bench, 8000)
    assert bench["decoder"].counters.crc_failures == before
    # delayed SDO responses: past the client's timeout
    assert emulator_control(ep, {"fault": "sdo_delay", "seconds": 0.6})["ok"]
    drive.sdo.RESPONSE_TIMEOUT = 0.3
    with pytest.raises(canopen.SdoCommunicationError):
        drive.sdo[0x6041].raw
    emulator_control(ep, {"fault": "clear"})
    time.sleep(0.8)  # the held response passes by
    drive.sdo.RESPONSE_TIMEOUT = 1.0
    assert drive.sdo[0x1018][1].raw == 0x0EAC
    # EMCY with FAULT
    emcy = []
    drive.emcy.add_callback(emcy.append)
    assert emulator_control(ep, {"fault": "emcy", "code": 12816})["ok"]
    assert wait_until(lambda: any(e.code == 12816 for e in emcy), 10.0)
    assert state_of(drive) == State402.FAULT
    drive.sdo[0x6040].raw = CONTROLWORD[PATH_TO_OPERATION_ENABLED[State402.FAULT]]
    # drive heartbeat stopped, then produced again
    seen = []
    bench["net"].subscribe(0x705, lambda can_id, data, ts: seen.append(time.monotonic()))
    assert emulator_control(ep, {"fault": "heartbeat_stop"})["ok"]
    stopped_at = time.monotonic()
    # a frame sent just before the stop may still be queued (late under load): quiet for 4 periods
    assert wait_until(lambda: time.monotonic() - max([stopped_at, *seen]) > 0.4, 10.0)
    heard_before = len(seen)
    emulator_control(ep, {"fault": "clear"})
    assert wait_until(lambda: len(seen) > heard_before, 10.0)
    # DAQ unplugged (its stable path disappears) and plugged in again as a new pty behind the same path
    link = ep["daq"]
    assert emulator_control(ep, {"fault": "daq_disconnect"})["ok"]
    assert not os.path.exists(link)
    with pytest.raises(serial.SerialException):
        for _ in range(100):
            bench["daq"].read(4096)
    reply = emulator_control(ep, {"fault": "daq_reconnect"})
    assert reply["ok"] and reply["daq"] == link and os.path.realpath(link) == reply["device"]
    bench["daq"].close()
    bench["daq"] = serial.Serial(reply["daq"], timeout=0.5)
    bench["decoder"] = FrameDecoder()
    # frames queued before the hang-up may still come first (those produced meanwhile are lost: a
    # gap, as on a real re-plugged DAQ); once the new port runs, the stream is contiguous
    read_samples(bench, 20000)
    index = read_samples(bench, 4000)[0]
    assert np.all(np.diff(index) == 1)
    assert emulator_control(ep, {"status": True})["faults"]["daq_disconnected"] is False


def test_control_socket_supply_faults(emulator, bench):
    """The supply drifts (MEAS:VOLT? and the drive's DC link follow, VOLT? stays) and trips (0 V, OUTP? 0),
    until clear; the status shows it."""
    _, ep = emulator
    drive = bench["drive"]
    port = serial.serial_for_url(ep["supply"], timeout=2.0)

    def ask(query: str) -> str:
        port.write(query.encode() + b"\n")
        return port.readline().decode().strip()

    def dc_link_v() -> float:
        read_samples(bench, 4096)  # a piece of plant: the firmware publishes what it measured
        return drive.sdo[0x6079].raw / 1000.0

    try:
        port.write(b"VOLT 12\nOUTP ON\n")
        assert float(ask("MEAS:VOLT?")) == pytest.approx(12.0, abs=0.01)
        assert emulator_control(ep, {"fault": "supply_voltage", "volts": 9.0})["ok"]
        assert float(ask("MEAS:VOLT?")) == pytest.approx(9.0, abs=0.01)
        assert float(ask("VOLT?")) == pytest.approx(12.0)
        assert wait_until(lambda: dc_link_v() == pytest.approx(9.0, abs=0.01), 20.0)
        supply = emulator_control(ep, {"status": True})["faults"]["supply"]
        assert supply == {"setpoint_v": 12.0, "output_on": True, "actual_v": 9.0, "drift_v": 9.0, "tripped": False}
        assert emulator_control(ep, {"fault": "supply_voltage", "volts": 99})["ok"] is False
        assert emulator_control(ep, {"fault": "supply_output_off"})["ok"]
        assert ask("OUTP?") == "0" and float(ask("MEAS:VOLT?")) == 0.0
        assert wait_until(lambda: dc_link_v() == 0.0, 20.0)
        assert emulator_control(ep, {"fault": "clear"})["ok"]
        assert emulator_control(ep, {"status": True})["faults"]["supply"]["tripped"] is False
        assert ask("OUTP?") == "0"  # a tripped supply does not switch itself back on
        port.write(b"OUTP ON\n")
        assert float(ask("MEAS:VOLT?")) == pytest.approx(12.0, abs=0.01)
        assert wait_until(lambda: dc_link_v() == pytest.approx(12.0, abs=0.01), 20.0)
    finally:
        port.close()


@pytest.fixture(scope="module")
def lone_emulator():
    """An emulator of its own at --speedup 0, that nobody reads unless a test does."""
    rig = EmulatorRig(speedup=0.0)
    try:
        yield rig
    finally:
        rig.stop()


def test_the_plant_keeps_real_time_while_nobody_reads_the_daq(lone_emulator):
    """--speedup 0 runs as fast as the DAQ is read; while nobody reads, it runs in real time and drops
    what the DAQ cannot deliver (a gap for the reader that comes back); read again, it runs fast again."""
    rig = lone_emulator
    rate_hz = rig.endpoints["sample_rate_hz"]

    def status() -> dict:
        reply = rig.control({"status": True})
        return {**reply["faults"], "at": reply["at"]}

    with DaqReader(rig.endpoints["daq"]) as reader:
        last = int(reader.read(4 * rate_hz, timeout_s=30.0).index[-1])  # a reader reads ...
        stopped_at = time.monotonic()  # ... then stops reading
        # the plant goes on alone: the DAQ's frames are dropped, at 1x real time (not as fast as it can)
        first = wait_until(lambda: (s := status())["daq_frames_dropped"] > 0 and s, 20.0, "frames dropped")
        later = wait_until(
            lambda: (s := status())["plant_samples"] - first["plant_samples"] >= rate_hz and s,
            20.0,
            "a second of plant time without a reader",
        )
        real_time_factor = (later["plant_samples"] - first["plant_samples"]) / rate_hz / (later["at"] - first["at"])
        assert 0.3 < real_time_factor < 2.0, real_time_factor
        assert later["daq_frames_dropped"] > first["daq_frames_dropped"]
        # the reader reads again: what was queued before the stall, then a gap, then the plant of now
        resumed_at = time.monotonic()
        before, after = [], None
        while after is None:
            block = reader.read_available(1 << 16, timeout_s=10.0)
            holes = np.flatnonzero(block.gap_before)
            if len(holes):
                before.append(block.index[: holes[0]])
                after = block.slice(int(holes[0]))
            else:
                before.append(block.index)
            assert sum(map(len, before)) < 30 * rate_hz, "no gap in 30 s of stream"
        stale = np.concatenate(before)
        np.testing.assert_array_equal(stale, np.arange(last + 1, last + 1 + len(stale)))  # in order, nothing lost
        wall_s = resumed_at - stopped_at
        advanced_s = (int(after.index[0]) - last) / rate_hz
        # about the wall time (and the buffers' couple of seconds, filled fast before the stall)
        assert 0.5 * wall_s <= advanced_s <= wall_s + 5.0, (advanced_s, wall_s)
        counters = reader.counters
        assert counters.overruns >= 1 and counters.sequence_gaps == 0 and counters.crc_failures == 0
        # read again, it runs as fast as it is read: 10 s of plant time in far less wall time
        t0, got, index = time.monotonic(), 0, int(after.index[-1])
        while got < 10 * rate_hz:
            block = reader.read_available(1 << 16, timeout_s=10.0)
            assert not block.gap_before.any() and int(block.index[0]) == index + 1
            index = int(block.index[-1])
            got += len(block)
        assert time.monotonic() - t0 < 5.0


def test_the_load_machines_fault_reaction_ends_without_a_reader(lone_emulator):
    """A master killed at speed (heartbeat gone, nobody reads the DAQ): the load machine brakes to
    standstill in plant time, which goes on in real time, and ends in FAULT by itself; a reset then works."""
    rig = lone_emulator
    can_ep = rig.endpoints["can"]

    def bus() -> CanBus:
        return CanBus(can_ep["interface"], can_ep["channel"], host=can_ep["host"], port=can_ep["port"]).connect()

    master = bus()
    load = LoadClient(master, rig.endpoints["load_node"], sdo_timeout_s=2.0)
    load.connect()
    load.enable()
    load.set_speed_rpm(2000)
    wait_until(lambda: load.read_status().speed_rpm > 1900, 30.0, "the load at speed (nobody reads the DAQ)")
    master.disconnect()  # as kill -9: the heartbeat stops, nothing else is said
    wait_until(
        lambda: rig.control({"status": True})["faults"]["load_state"] == "fault",
        10.0,
        "the load's fault reaction ended by itself",
    )
    again = bus()
    try:
        load = LoadClient(again, rig.endpoints["load_node"], sdo_timeout_s=2.0)
        load.connect()
        assert load.fault_reset() is True
        assert load.state() is State402.SWITCH_ON_DISABLED
        load.disarm_heartbeat_consumer()
    finally:
        again.disconnect()


def test_sigterm_exits_cleanly(emulator, bench):
    proc, _ = emulator
    bench["heartbeat"].stop()
    bench["daq"].close()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
