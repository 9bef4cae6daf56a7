"""CANopen drivers against the emulator's own CiA 402 devices on python-can virtual buses (no mocks).

The devices are plant_emulator's DriveFirmware and LoadMachineFirmware: canopen LocalNodes that load
the same EDS files as the clients and walk the same CiA 402 transition table, the very objects the
emulated bench serves over socketcand. So these tests exercise the real SDO protocol, NMT,
heartbeat and EMCY paths end to end, against the device the service meets on the emulated bench.
"""

from __future__ import annotations

import math
import struct
import threading
import time
import zlib

import can
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from drivers import DRIVE_EDS, LOAD_EDS, cia402_master, lut_image
from drivers.canopen_bus import CanBus
from drivers.cia402 import CONTROLWORD, Command402, State402
from drivers.drive import DriveClient, DriveStatus, LutInForce
from drivers.errors import (
    DriveFaultError,
    FaultReactionActiveError,
    ForeignMasterError,
    HeartbeatMissingError,
    NotConnectedError,
    SdoAbortError,
    SdoError,
    SdoTimeoutError,
    StateTransitionError,
)
from drivers.load_machine import LoadClient, LoadStatus
from plant_emulator import physics as ph
from plant_emulator.drive_firmware import DriveFirmware
from plant_emulator.load_machine import LoadMachineFirmware
from plant_emulator.socketcand_server import SocketcandServer
from tests.support.drivers_peers import EmulatedDevice, unique_channel
from tests.support.waiting import wait_until

DRIVE_NODE = 5
LOAD_NODE = 6
SERVICE_NODE = 1


@pytest.fixture
def channel():
    return unique_channel()


@pytest.fixture
def bus(channel):
    with CanBus("virtual", channel, service_node_id=SERVICE_NODE, heartbeat_period_ms=50) as can_bus:
        yield can_bus


@pytest.fixture
def drive_peer(channel):
    peer = EmulatedDevice(DriveFirmware, channel, DRIVE_NODE, DRIVE_EDS)
    yield peer
    peer.close()


@pytest.fixture
def drive(bus, drive_peer):
    client = DriveClient(bus, DRIVE_NODE, sdo_timeout_s=2.0)
    client.connect()
    yield client
    client.close()


@pytest.fixture
def load_peer(channel):
    peer = EmulatedDevice(LoadMachineFirmware, channel, LOAD_NODE, LOAD_EDS, ramp_rpm_per_s=20000.0)
    yield peer
    peer.close()


def test_connect_configures_heartbeat_consumer_and_reads_rated_torque(drive, drive_peer):
    assert drive_peer.node.nmt.state == "OPERATIONAL"
    assert drive_peer.device.stored(0x1016, 1) == (SERVICE_NODE << 16) | 500
    assert drive.rated_torque_nm == pytest.approx(5.0)
    assert drive.heartbeat_period_ms == int(drive_peer.node.object_dictionary[0x1017].default)  # 100


def test_enable_walks_to_operation_enabled_and_disable_returns(drive, drive_peer):
    assert drive.state() is State402.SWITCH_ON_DISABLED
    drive.enable(timeout_s=2.0)
    assert drive.state() is State402.OPERATION_ENABLED
    assert drive_peer.device.stored(0x6060) == 4
    assert drive_peer.writes_to(0x6040) == [
        CONTROLWORD[Command402.SHUTDOWN],
        CONTROLWORD[Command402.SWITCH_ON],
        CONTROLWORD[Command402.ENABLE_OPERATION],
    ]
    drive.set_torque_nm(1.0)
    drive.set_injection(0.01, 0.02)
    drive.disable(timeout_s=2.0)
    assert drive.state() is State402.SWITCH_ON_DISABLED
    # the safety path made the drive harmless before switching the power stage off
    assert drive_peer.device.stored(0x6071) == 0
    assert drive_peer.device.stored(0x2000, 2) == 0


def test_enable_refuses_a_fault_and_only_fault_reset_clears_it(drive, drive_peer):
    """Issue 8: a drive fault is acknowledged by a person; enable() never resets it by itself."""
    drive_peer.device.fault(0x3210)  # DC link over-voltage
    with pytest.raises(DriveFaultError, match=r"drive node 5 in FAULT.*fault reset"):
        drive.enable(timeout_s=2.0)
    assert CONTROLWORD[Command402.FAULT_RESET] not in drive_peer.writes_to(0x6040)
    assert drive_peer.device.state is State402.FAULT
    assert drive.fault_reset(timeout_s=2.0) is True
    assert drive_peer.writes_to(0x6040)[-2:] == [0x0000, CONTROLWORD[Command402.FAULT_RESET]]
    assert drive_peer.device.error_code == 0
    drive.enable(timeout_s=2.0)
    assert drive_peer.device.state is State402.OPERATION_ENABLED
    assert drive.fault_reset() is False  # not in FAULT: nothing sent


def test_enable_times_out_with_a_clear_error_when_the_device_does_not_follow(drive, drive_peer):
    drive_peer.node._write_callbacks.remove(drive_peer.device._on_write)  # device ignores controlwords now
    with pytest.raises(StateTransitionError, match=r"drive node 5: .*SWITCH_ON_DISABLED.*after SHUTDOWN"):
        drive.enable(timeout_s=0.2)


def test_torque_is_sent_in_per_mille_of_rated_torque(drive, drive_peer):
    assert drive.set_torque_nm(2.5) == 500
    assert drive.set_torque_nm(-5.0) == -1000
    drive.set_torque_nm(0.0012)
    assert drive_peer.writes_to(0x6071) == [500, -1000, 0]
    # what the control loop publishes, served live by SDO: 0x6077 = 498 per mille, 0x6079 = 12000 mV
    drive_peer.device.publish(speed_rpm=2001.0, torque_nm=2.49, udc_v=12.0, ud_ref_v=-1.5, uq_ref_v=7.25)
    status = drive.read_status()
    assert isinstance(status, DriveStatus)
    assert status == DriveStatus(
        state=State402.SWITCH_ON_DISABLED,
        torque_nm=pytest.approx(2.49),
        speed_rpm=2001.0,
        udc_v=pytest.approx(12.0),
        ud_ref_v=pytest.approx(-1.5),
        uq_ref_v=pytest.approx(7.25),
    )


@pytest.mark.parametrize("torque_nm", [5.01, -6.0, math.nan, math.inf])
def test_out_of_range_torque_is_rejected_before_sending(drive, drive_peer, torque_nm):
    before = len(drive_peer.writes)
    with pytest.raises(ValueError, match="outside the drive's range"):
        drive.set_torque_nm(torque_nm)
    time.sleep(0.05)
    assert len(drive_peer.writes) == before


def test_device_refusal_names_object_and_abort_meaning(drive, drive_peer):
    with pytest.raises(SdoAbortError) as info:
        drive.write(0x6071, 0, 1500)  # bypasses the client-side check on purpose
    message = str(info.value)
    assert "0x6071:00 'Target torque'" in message
    assert "0x06090030" in message and "Value range of parameter exceeded" in message
    assert info.value.abort_code == 0x06090030


def test_set_injection_writes_real32_pair_and_commits(drive, drive_peer):
    before = drive.setpoints_written
    assert drive.set_injection(0.0123, -0.0456) == 1  # one commit = one setpoint (one sync toggle)
    assert drive.setpoints_written == before + 1
    assert drive_peer.writes_to(0x2000, 3) == [pytest.approx(0.0123, rel=1e-6)]
    assert drive_peer.writes_to(0x2000, 4) == [pytest.approx(-0.0456, rel=1e-6)]
    assert drive_peer.writes_to(0x2000, 2) == []  # the mode is a separate setpoint
    assert drive_peer.writes_to(0x2000, 7) == [1]
    raw = drive_peer.node.data_store[0x2000][3]
    assert len(raw) == 4 and struct.unpack("<f", raw)[0] == pytest.approx(0.0123, rel=1e-6)
    drive.set_injection_mode("manual")
    assert drive_peer.writes_to(0x2000, 2) == [1]
    assert drive.set_injection(0.02, 0.0) == 1
    assert drive_peer.writes_to(0x2000, 7) == [1, 1]
    assert drive.commit_count() == 2
    assert drive.setpoints_written == before + 3
    index_order = [(i, s) for (i, s, _v) in drive_peer.writes if i == 0x2000]
    assert index_order == [(0x2000, 3), (0x2000, 4), (0x2000, 7), (0x2000, 2), (0x2000, 3), (0x2000, 4), (0x2000, 7)]
    drive.injection_off()
    assert drive_peer.device.stored(0x2000, 2) == 0


def test_further_orders_are_staged_in_0x2002_and_applied_with_the_commit(drive, drive_peer):
    """set_injection with further orders: 0x2002 written (only where it changed), one commit (one sync
    toggle) applies every order at once; the control loop gets each order's theta, all scaled by one
    factor so that the sum of |theta| is at most gamma_max (|v_inj| <= gamma_max at every angle)."""
    before = drive.setpoints_written
    drive.set_gamma_max_rad(0.01)
    drive.set_injection(0.006, -0.008, further=((12, 0.003, 0.004),))  # |theta| 0.01 and 0.005
    assert drive.setpoints_written == before + 1
    assert drive_peer.writes_to(0x2002, 1) == [12] and drive_peer.writes_to(0x2002, 4) == [0]
    drive.set_injection_mode("manual")
    sp = ph.new_setpoints(12.0)
    while drive_peer.device.has_pending():  # the drive's control loop takes one event per piece
        drive_peer.device.chunk_setpoints(sp, 12.0)
    drive_peer.device.chunk_setpoints(sp, 12.0)
    k = 0.01 / 0.015  # the sum of |theta| was 0.015
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((0.006 * k, -0.008 * k), rel=1e-6)
    assert (sp[ph.S_XH_ORDER], sp[ph.S_XH_COS], sp[ph.S_XH_SIN]) == pytest.approx((12, 0.003 * k, 0.004 * k), rel=1e-6)
    assert sp[ph.S_XH_ORDER + 1] == 0 and sp[ph.S_XH_ORDER + 2] == 0
    # the same further orders again: 0x2002 not written again; none: slot 1 cleared, nothing else
    writes = len([w for w in drive_peer.writes if w[0] == 0x2002])
    drive.set_injection(0.001, 0.0, further=((12, 0.003, 0.004),))
    assert len([w for w in drive_peer.writes if w[0] == 0x2002]) == writes
    drive.set_injection(0.001, 0.0)
    assert len([w for w in drive_peer.writes if w[0] == 0x2002]) == writes + 3
    assert drive_peer.writes_to(0x2002, 1) == [12, 0]
    # one theta per order: the main order again, or an order twice, is refused (by us, and by the drive)
    with pytest.raises(ValueError, match="twice"):
        drive.set_injection(0.0, 0.0, further=((12, 0.0, 0.0), (12, 0.001, 0.0)))
    drive_peer.device.chunk_setpoints(sp, 12.0)
    commits = drive.commit_count()
    with pytest.raises(SdoAbortError):
        drive.set_injection(0.0, 0.0, further=((6, 0.001, 0.0),))  # 6 is 0x2000:1, the main order
    assert drive.commit_count() == commits  # nothing applied


def test_injection_parameters(drive, drive_peer):
    drive.set_harmonic_order(12)
    drive.set_gamma_max_rad(0.1)
    drive.set_decoupling(True)
    assert drive_peer.device.stored(0x2000, 1) == 12
    assert drive_peer.device.stored(0x2000, 5) == pytest.approx(0.1, rel=1e-6)
    assert drive_peer.device.gamma_max_rad == pytest.approx(0.1, rel=1e-6)
    assert drive_peer.device.stored(0x2000, 6) == 1
    drive.set_decoupling(False)
    assert drive_peer.device.stored(0x2000, 6) == 0
    for bad in (0, 256, 2.5):
        with pytest.raises(ValueError):
            drive.set_harmonic_order(bad)
    with pytest.raises(ValueError):
        drive.set_gamma_max_rad(-0.1)


def test_sdo_timeout_on_missing_node_names_the_object(bus, drive_peer):
    ghost = DriveClient(bus, 42, sdo_timeout_s=0.1)
    t0 = time.monotonic()
    with pytest.raises(SdoTimeoutError) as info:
        ghost.connect()
    assert time.monotonic() - t0 < 1.0
    message = str(info.value)
    # the identity is read first, before anything is written to a node
    assert "node 42" in message and "0x1018:01" in message and "Identity object.Vendor-ID" in message
    assert "no SDO response within 0.1 s" in message
    assert not ghost.connected  # a failed connect leaves nothing attached


def test_disable_tries_every_step_and_raises_the_first_error(bus, channel):
    peer = EmulatedDevice(DriveFirmware, channel, DRIVE_NODE, DRIVE_EDS)
    try:
        client = DriveClient(bus, DRIVE_NODE, sdo_timeout_s=0.1)
        client.connect()
        client.enable()

        # the injection record is refused from now on; torque 0 and disable voltage must still go out
        def refuse_injection(index, subindex, od, data, **_kwargs):
            if index == 0x2000:
                raise SdoAbortedError(0x08000022)  # "because of the present device state"

        peer.node._write_callbacks.insert(0, refuse_injection)
        with pytest.raises(SdoAbortError, match=r"0x2000:02 'Harmonic injection.Injection mode'.*0x08000022"):
            client.disable()
        assert peer.device.stored(0x6071) == 0
        assert peer.device.state is State402.SWITCH_ON_DISABLED
        client.close()
    finally:
        peer.close()


def test_can_bus_produces_service_heartbeat(channel):
    peer = EmulatedDevice(DriveFirmware, channel, DRIVE_NODE, DRIVE_EDS)
    frames: list[tuple[float, bytes]] = []
    peer.network.subscribe(0x701, lambda can_id, data, ts: frames.append((time.monotonic(), bytes(data))))
    try:
        with CanBus("virtual", channel, service_node_id=1, heartbeat_period_ms=50):
            assert wait_until(lambda: len(frames) >= 4, 5.0)
        assert all(data == b"\x05" for _, data in frames)
        stopped_at = len(frames)
        time.sleep(0.2)
        assert len(frames) <= stopped_at + 1  # heartbeat ends with the connection
    finally:
        peer.close()


def test_drive_heartbeat_monitoring_and_emcy(drive, drive_peer):
    assert wait_until(drive.heartbeat_alive, 5.0)
    assert wait_until(lambda: drive.nmt_state == 5, 5.0)  # the NMT start command took effect
    drive_peer.device.heartbeat_lost()  # the drive's own reaction: FAULT and EMCY 0x8130
    assert wait_until(lambda: len(drive.emcy_log) == 1, 5.0)
    assert drive.emcy_log[0].code == 0x8130
    assert drive.state() is State402.FAULT
    drive_peer.device.shutdown()  # the producer heartbeat stops
    assert wait_until(lambda: not drive.heartbeat_alive(), 10.0)  # at least HEARTBEAT_ALIVE_MIN_S


def test_connect_waits_for_the_first_heartbeat_and_names_a_silent_device(bus, drive_peer):
    heard: list[float] = []
    bus.network.subscribe(0x700 + DRIVE_NODE, lambda can_id, data, ts: heard.append(time.monotonic()))
    drive_peer.node.nmt.stop_heartbeat()  # answers SDO, never heard on 0x705
    stopped_at = time.monotonic()
    # a heartbeat sent just before the stop can still sit in the bus queue (late under load): wait until
    # the line has been quiet for 5 producer periods, so the client's wait can only end by its timeout
    assert wait_until(lambda: time.monotonic() - max([stopped_at, *heard]) > 0.5, 10.0)
    client = DriveClient(bus, DRIVE_NODE, sdo_timeout_s=2.0)
    with pytest.raises(HeartbeatMissingError, match=r"drive node 5: answers SDO but sent no heartbeat within"):
        client.connect()
    assert not client.connected  # nothing half-open
    drive_peer.node.nmt.start_heartbeat(100)
    client.connect()
    assert client.heartbeat_alive()  # ready means heard: the interlock's first round passes


def test_load_client_enables_and_sets_speed(bus, load_peer):
    load = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
    load.connect()
    load.enable()
    assert load_peer.device.state is State402.OPERATION_ENABLED
    assert load_peer.device.stored(0x6060) == 3
    assert load.set_speed_rpm(2000.4) == 2000
    assert load_peer.writes_to(0x60FF) == [2000]
    load_peer.device.publish(speed_rpm=1998.0, torque_nm=-0.25)  # served as 1998 rpm and -250 mNm
    status = load.read_status()
    assert status == LoadStatus(state=State402.OPERATION_ENABLED, speed_rpm=1998.0, torque_nm=pytest.approx(-0.25))
    load.disable()
    assert load_peer.writes_to(0x60FF)[-1] == 0
    assert load_peer.device.state is State402.SWITCH_ON_DISABLED
    load.close()


def test_drive_and_load_share_one_bus_concurrently(bus, drive, drive_peer, load_peer):
    load = LoadClient(bus, LOAD_NODE)
    load.connect()
    errors: list[BaseException] = []

    def poll_drive():
        try:
            for _ in range(20):
                drive.read_status()
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    thread = threading.Thread(target=poll_drive)
    thread.start()
    for speed in range(0, 2000, 100):
        load.set_speed_rpm(speed)
    thread.join(10)
    assert not errors
    assert load_peer.writes_to(0x60FF) == list(range(0, 2000, 100))
    load.close()


def test_bus_passes_only_the_options_that_are_set():
    # socketcand: low-latency TCP by default (drivers.canopen_bus.INTERFACE_DEFAULTS), overridable
    assert CanBus("socketcand", "can0", host="127.0.0.1", port=29536).bus_kwargs() == {
        "interface": "socketcand",
        "channel": "can0",
        "host": "127.0.0.1",
        "port": 29536,
        "tcp_tune": True,
    }
    assert CanBus("socketcand", "can0", host="127.0.0.1", port=1, tcp_tune=False).bus_kwargs()["tcp_tune"] is False
    assert CanBus("virtual", "bench").bus_kwargs() == {"interface": "virtual", "channel": "bench"}
    assert CanBus("pcan", "PCAN_USBBUS1", bitrate=500_000).bus_kwargs()["bitrate"] == 500_000


def test_clients_need_a_connected_bus(channel):
    bus = CanBus("virtual", channel)
    with pytest.raises(NotConnectedError, match="not connected"):
        bus.network
    with pytest.raises(NotConnectedError):
        DriveClient(bus, DRIVE_NODE).connect()
    with pytest.raises(NotConnectedError, match="drive node 5: not connected"):
        DriveClient(bus, DRIVE_NODE).set_torque_nm(1.0)


def test_lut_download_is_segmented_and_crc_checked(drive, drive_peer):
    n_t, n_n, n_u = 8, 6, 3  # 144 cells: a 1509-byte image, many segments
    cells = np.arange(n_t * n_n * n_u, dtype=float)
    blob = lut_image.encode(
        6,
        np.linspace(0.5, 4.0, n_t),
        np.linspace(500.0, 3000.0, n_n),
        [10.0, 12.0, 14.0],
        1e-4 * cells,
        -2e-4 * cells,
        map_id=12,
    )
    assert len(blob) > 1000
    assert drive.lut_in_force() == LutInForce(map_id=0, crc32=0, status="none")
    held = drive.download_lut(blob)
    assert held == LutInForce(map_id=12, crc32=zlib.crc32(blob[:-4]), status="in_force")
    assert drive_peer.writes_to(0x2001, 1) == [blob]
    assert drive_peer.device.lut.crc == held.crc32  # the drive decoded it and holds it in force
    # a malformed image is refused by the drive itself (SDO abort), and its LUT stays
    with pytest.raises(SdoAbortError, match="0x08000020"):
        drive.download_lut(blob[:-1] + bytes([blob[-1] ^ 1]))
    assert drive.lut_in_force() == LutInForce(map_id=12, crc32=held.crc32, status="last_download_refused")
    drive_peer.node._write_callbacks.remove(drive_peer.device._on_write)  # the device stops updating its CRC
    with pytest.raises(SdoError, match="LUT CRC-32 read-back"):
        drive.download_lut(b"other table")


def test_load_machine_reports_its_speed_ramp(load_peer, bus):
    load = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
    load.connect()
    try:
        assert load.read(0x2000) == 20000  # load.eds's manufacturer object, rpm/s
    finally:
        load.close()


# --- fault reaction: a reset that comes while the load machine still brakes ----------------------------


def _count_statusword_reads(peer: EmulatedDevice) -> list[int]:
    """Statusword reads the device served (a read callback ahead of the device's own, answering nothing)."""
    reads: list[int] = []

    def count(index, subindex, od, **_kwargs):
        if index == 0x6041:
            reads.append(1)
        return None

    peer.node._read_callbacks.insert(0, count)
    return reads


def test_fault_reset_waits_for_the_fault_reaction_to_end_then_resets(bus, load_peer):
    load = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
    load.connect()
    try:
        load.enable()
        load_peer.device.publish(speed_rpm=2000.0, torque_nm=0.0)
        load_peer.device.heartbeat_lost()  # enabled at speed: it brakes to standstill first
        assert load_peer.device.state is State402.FAULT_REACTION_ACTIVE
        reads = _count_statusword_reads(load_peer)
        outcome: dict = {}
        resetting = threading.Thread(
            target=lambda: outcome.update(reset=load.fault_reset(fault_reaction_timeout_s=60.0))
        )
        resetting.start()
        # the reset waits, reading the statusword, and sends nothing while the machine still brakes
        wait_until(lambda: len(reads) >= 3, 10.0, "the reset polling the statusword")
        assert CONTROLWORD[Command402.FAULT_RESET] not in load_peer.writes_to(0x6040)
        load_peer.device.publish(speed_rpm=0.0, torque_nm=0.0)  # standstill: the reaction ends in FAULT
        resetting.join(20.0)
        assert outcome == {"reset": True}
        assert load_peer.writes_to(0x6040)[-2:] == [0x0000, CONTROLWORD[Command402.FAULT_RESET]]
        assert load_peer.device.state is State402.SWITCH_ON_DISABLED
    finally:
        load.close()


def test_fault_reset_during_a_fault_reaction_that_goes_on_says_what_it_waits_for(bus, load_peer):
    load = LoadClient(bus, LOAD_NODE, sdo_timeout_s=2.0)
    load.connect()
    try:
        load.enable()
        load_peer.device.heartbeat_lost()  # no standstill is published: it brakes on
        started = time.monotonic()
        with pytest.raises(FaultReactionActiveError) as info:
            load.fault_reset(fault_reaction_timeout_s=0.3)
        assert time.monotonic() - started >= 0.3  # it did wait for the reaction first
        message = str(info.value)
        assert message.startswith(
            "load machine node 6 is still braking to standstill after its fault (FAULT_REACTION_ACTIVE"
        )
        assert "EMCY 0x8130" in message and message.endswith("try the reset again when it has stopped")
        assert isinstance(info.value, StateTransitionError)  # callers that knew the old error still do
        assert CONTROLWORD[Command402.FAULT_RESET] not in load_peer.writes_to(0x6040)
        assert load_peer.device.state is State402.FAULT_REACTION_ACTIVE
        assert cia402_master.FAULT_REACTION_WAIT_S >= 10.0  # the default waits for a real braking
    finally:
        load.close()


# --- one master per node id on the bus ---------------------------------------------------------------------


def test_a_second_master_with_our_node_id_is_refused_at_connect(bus, drive_peer):
    heard: list[float] = []
    drive_peer.network.subscribe(0x701, lambda can_id, data, ts: heard.append(time.monotonic()))
    wait_until(lambda: len(heard) >= 2, 5.0, "the first master's heartbeat")
    second = CanBus("virtual", bus.channel, service_node_id=SERVICE_NODE, heartbeat_period_ms=50)
    with pytest.raises(ForeignMasterError, match=rf"another master sends heartbeats as node 1 on {bus.channel}"):
        second.connect()
    assert not second.connected and second.foreign_master() is None
    # it listened before sending: the first master never heard a heartbeat with its own id
    assert bus.foreign_master() is None
    # another node id is another master, not ours: both run, neither reports the other
    other = CanBus("virtual", bus.channel, service_node_id=2, heartbeat_period_ms=50).connect()
    try:
        seen_2: list[float] = []
        drive_peer.network.subscribe(0x702, lambda can_id, data, ts: seen_2.append(time.monotonic()))
        wait_until(lambda: len(seen_2) >= 5, 5.0, "node 2's heartbeats")
        assert bus.foreign_master() is None and other.foreign_master() is None
    finally:
        other.disconnect()


def test_a_running_bus_names_a_master_that_appears_with_its_id(bus):
    assert bus.foreign_master() is None
    # a master that does not listen first (an older tool, a PLC configured as node 1)
    intruder = can.Bus(interface="virtual", channel=bus.channel)
    task = intruder.send_periodic(can.Message(arbitration_id=0x701, data=[0x05], is_extended_id=False), 0.05)
    try:
        described = wait_until(bus.foreign_master, 5.0, "the second master named")
        assert described.startswith(f"another master sends heartbeats as node 1 on {bus.channel}")
    finally:
        task.stop()
        intruder.shutdown()
    # gone again: reported no more once its last heartbeat is older than the hold time
    wait_until(lambda: bus.foreign_master() is None, 10.0, "the report cleared")
    assert bus.heartbeat_producing()


def test_over_socketcand_a_bus_does_not_hear_itself_but_hears_a_second_master():
    """The emulator's socketcand server sends a client's frames to the other clients only, so our own
    heartbeat never comes back to us; a second client with our node id is heard."""
    server = SocketcandServer(unique_channel()).start()
    first = CanBus(
        "socketcand", "can0", host=server.host, port=server.port, service_node_id=SERVICE_NODE, heartbeat_period_ms=50
    )
    try:
        first.connect()  # no refusal: it does not hear itself
        watcher = CanBus(
            "socketcand", "can0", host=server.host, port=server.port, service_node_id=9, heartbeat_period_ms=50
        ).connect()
        try:
            heard: list[float] = []
            watcher.network.subscribe(0x701, lambda can_id, data, ts: heard.append(time.monotonic()))
            wait_until(lambda: len(heard) >= 10, 10.0, "ten of the first master's heartbeats on the wire")
            assert first.foreign_master() is None
            second = CanBus(
                "socketcand",
                "can0",
                host=server.host,
                port=server.port,
                service_node_id=SERVICE_NODE,
                heartbeat_period_ms=50,
            )
            with pytest.raises(ForeignMasterError, match="another master sends heartbeats as node 1 on can0"):
                second.connect()
            assert first.foreign_master() is None  # the refused one sent nothing
        finally:
            watcher.disconnect()
    finally:
        first.disconnect()
        server.close()
