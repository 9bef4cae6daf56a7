"""plant_emulator's wire servers in-process: socketcand bridge, SCPI supply, DAQ pty."""

from __future__ import annotations

import os
import select
import socket
import threading
import time
import uuid

import can
import numpy as np
import pytest

from drivers.daq_protocol import FrameDecoder, encode_frames
from plant_emulator.daq_stream import QUEUED, STALLED, STOPPED, DaqPty
from plant_emulator.scpi_supply import DcSupply
from plant_emulator.socketcand_server import SocketcandServer, format_frame, parse_send


def test_frame_text_round_trip():
    msg = parse_send("send 705 3 1 a ff")
    assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (0x705, b"\x01\x0a\xff", False)
    msg.timestamp = 1700000000.25
    assert format_frame(msg) == "< frame 705 1700000000.250000 010AFF >"
    for bad in ("send 705 2 1", "send xyz 1 1", "send 705 9 1 2 3 4 5 6 7 8 9", "send 800 0"):
        with pytest.raises(ValueError):
            parse_send(bad)


@pytest.fixture()
def server():
    channel = f"test-{uuid.uuid4().hex}"
    srv = SocketcandServer(channel).start()
    internal = can.Bus(interface="virtual", channel=channel)
    try:
        yield srv, internal
    finally:
        internal.shutdown()
        srv.close()


def client(srv) -> can.BusABC:
    return can.Bus(interface="socketcand", host=srv.host, port=srv.port, channel="can0")


def recv_until(bus, can_id, timeout=2.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == can_id:
            return msg
    return None


def test_clients_and_internal_bus_see_each_other(server):
    srv, internal = server
    a, b = client(srv), client(srv)
    try:
        time.sleep(0.3)  # handshake grace period
        a.send(can.Message(arbitration_id=0x605, data=[0x40, 0x18, 0x10, 1, 0, 0, 0, 0], is_extended_id=False))
        got_internal = recv_until(internal, 0x605)
        got_b = recv_until(b, 0x605)
        assert got_internal is not None and bytes(got_internal.data) == bytes([0x40, 0x18, 0x10, 1, 0, 0, 0, 0])
        assert got_b is not None and bytes(got_b.data) == bytes(got_internal.data)
        internal.send(
            can.Message(arbitration_id=0x585, data=[0x43, 0x18, 0x10, 1, 0xAC, 0x0E, 0, 0], is_extended_id=False)
        )
        for bus in (a, b):
            got = recv_until(bus, 0x585)
            assert got is not None and got.data[4] == 0xAC
    finally:
        a.shutdown()
        b.shutdown()


def test_malformed_input_and_disconnects_do_not_kill_the_server(server):
    srv, internal = server
    raw = socket.create_connection((srv.host, srv.port))
    assert raw.recv(64) == b"< hi >"
    raw.sendall(b"< open can0 >")
    assert raw.recv(64) == b"< ok >"
    raw.sendall(b"< rawmode >")
    assert raw.recv(64) == b"< ok >"
    raw.sendall(b"garbage < send zz 1 1 > < send 123 2 1 > < bogus > < send 123 1 7 >")
    got = recv_until(internal, 0x123)
    assert got is not None and bytes(got.data) == b"\x07"
    raw.close()
    time.sleep(0.2)
    c = client(srv)  # still serving
    c.shutdown()


def test_scpi_supply_commands():
    s = DcSupply(12.0)
    assert s.handle_line("*IDN?") == ["ripplecal,emulated-supply,0,0.1"]
    assert s.handle_line("OUTP?") == ["0"] and s.actual_v() == 0.0
    assert s.handle_line("VOLT 24.5") == []
    assert s.handle_line("volt?;outp on;OUTPut?") == ["24.5000", "1"]
    assert float(s.handle_line("MEAS:VOLT?")[0]) == pytest.approx(24.5, abs=0.01)
    assert s.actual_v() == 24.5
    assert s.handle_line("VOLT 61") == [] and s.actual_v() == 24.5
    assert s.handle_line("FOO 1") == []
    assert s.handle_line("SYST:ERR?") == ['-222,"Data out of range"']
    assert s.handle_line("SYST:ERR?")[0].startswith("-113")
    assert s.handle_line("SYST:ERR?") == ['0,"No error"']


def test_pty_paced_drops_whole_frames_and_blocking_waits():
    pty = DaqPty(max_pending_bytes=1200)
    try:
        frames = encode_frames(np.arange(4000), np.zeros(4000), np.zeros(4000), np.zeros(4000))
        for k in range(10):  # nobody reads: the pty fills, then whole frames are dropped
            pty.write_paced(frames[k * 4800 : (k + 1) * 4800])
        assert pty.frames_dropped > 0
        fd = os.open(pty.name, os.O_RDONLY | os.O_NONBLOCK)
        try:
            data = b""
            for _ in range(50):
                try:
                    data += os.read(fd, 65536)
                except BlockingIOError:
                    pty.write_paced(b"")
                    time.sleep(0.01)
            dec = FrameDecoder()
            s = dec.feed(data)
            assert len(s) > 0 and dec.counters.crc_failures == 0 and dec.counters.sequence_gaps >= 1
        finally:
            os.close(fd)
        stop = threading.Event()
        t = threading.Timer(0.3, stop.set)
        t.start()
        # blocking write with no reader returns False once stopped instead of hanging
        assert pty.write_blocking(frames * 20, stop) is False
        t.cancel()
    finally:
        pty.close()


def test_scpi_supply_faults_drift_and_trip():
    s = DcSupply(12.0)
    s.handle_line("VOLT 12;OUTP ON")
    s.drift_to(9.0)  # the output drifts; the setpoint stays
    assert s.handle_line("VOLT?") == ["12.0000"]
    assert float(s.handle_line("MEAS:VOLT?")[0]) == pytest.approx(9.0, abs=0.01) and s.actual_v() == 9.0
    s.handle_line("VOLT 14")  # a new setpoint does not repair it either
    assert s.actual_v() == 9.0 and s.handle_line("VOLT?") == ["14.0000"]
    s.trip_output()  # the protection trips: 0 V, OUTP? 0, OUTP ON refused
    assert s.handle_line("OUTP?;MEAS:VOLT?") == ["0", "0.0000"] and s.actual_v() == 0.0
    assert s.handle_line("OUTP ON;OUTP?") == ["0"]
    assert s.handle_line("SYST:ERR?") == ['-221,"Settings conflict; output protection tripped"']
    s.handle_line("*RST")  # a reset command does not repair the supply
    assert s.snapshot()["tripped"] and s.snapshot()["drift_v"] == 9.0
    s.clear_faults()  # repaired: a tripped output stays off until switched on
    assert s.handle_line("OUTP?") == ["0"] and s.actual_v() == 0.0
    s.handle_line("VOLT 12;OUTP ON")
    assert s.actual_v() == 12.0 and float(s.handle_line("MEAS:VOLT?")[0]) == pytest.approx(12.0, abs=0.01)
    assert s.snapshot() == {"setpoint_v": 12.0, "output_on": True, "actual_v": 12.0, "drift_v": None, "tripped": False}
    with pytest.raises(ValueError):
        s.drift_to(61.0)


def test_pty_offer_waits_while_read_and_gives_up_once_nobody_reads():
    """--speedup 0's writer: backpressure while a reader reads; STALLED (the batch not queued) once the pty
    has taken nothing for stall_s, so the emulator can go on in real time (process.py _run_fast)."""
    pty = DaqPty()
    stop = threading.Event()
    batch = encode_frames(np.arange(4096), np.zeros(4096), np.zeros(4096), np.zeros(4096))
    try:
        pty.start_writer(stop)
        stall_s = 0.3
        results = []
        while len(results) < 50 and (not results or results[-1] == QUEUED):  # nobody reads: it fills, then stalls
            results.append(pty.offer(batch, stall_s=stall_s))
        assert results[-1] == STALLED and results.count(STALLED) == 1
        assert time.monotonic() - pty.write_progress_at > stall_s  # the pty took nothing for that long
        progress_before = pty.write_progress_at
        fd = os.open(pty.name, os.O_RDONLY | os.O_NONBLOCK)
        try:
            got = 0
            while pty.write_progress_at == progress_before or got < len(batch):  # a reader reads again
                try:
                    got += len(os.read(fd, 1 << 16))
                except BlockingIOError:
                    select.select([fd], [], [], 0.05)
            assert pty.write_progress_at > progress_before
            assert pty.offer(batch, stall_s=stall_s) == QUEUED  # it takes batches again
        finally:
            os.close(fd)
        pty.drop(batch)
        assert pty.frames_dropped == 4096
        stop.set()
        assert pty.offer(batch) == STOPPED
    finally:
        stop.set()
        pty.close()


# -- slcan (plant_emulator/slcan_server.py), against python-can's own slcan interface ------------------


def test_slcan_line_round_trip_and_refusals():
    from plant_emulator.slcan_server import format_frame as slcan_line
    from plant_emulator.slcan_server import parse_frame

    msg = parse_frame("t70530A0BFF")
    assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (0x705, b"\x0a\x0b\xff", False)
    assert slcan_line(msg) == "t70530A0BFF"
    ext = parse_frame("T1ABCDEF120102")
    assert (ext.arbitration_id, ext.is_extended_id, slcan_line(ext)) == (0x1ABCDEF1, True, "T1ABCDEF120102")
    for bad in ("t7053010", "t80000", "t70590102030405060708090A", "t7"):
        with pytest.raises(ValueError):
            parse_frame(bad)


def test_slcan_adapter_carries_frames_both_ways_and_refuses_bad_lines():
    from plant_emulator.slcan_server import SlcanServer

    channel = f"test-{uuid.uuid4().hex}"
    srv = SlcanServer(channel).start()
    internal = can.Bus(interface="virtual", channel=channel)
    bus = can.Bus(interface="slcan", channel=srv.url, bitrate=500000, sleep_after_open=0)
    try:
        bus.send(can.Message(arbitration_id=0x605, data=b"\x40\x00\x10\x00\x00\x00\x00\x00", is_extended_id=False))
        got = recv_until(internal, 0x605)
        assert got is not None and bytes(got.data) == b"\x40\x00\x10\x00\x00\x00\x00\x00"
        internal.send(can.Message(arbitration_id=0x585, data=b"\x43\x00\x10\x00\x92\x01\x02\x00", is_extended_id=False))
        back = recv_until(bus, 0x585)
        assert back is not None and bytes(back.data) == b"\x43\x00\x10\x00\x92\x01\x02\x00"
        # a raw client: every command answered, a malformed frame or an unknown command refused with BEL
        raw = socket.create_connection((srv.host, srv.port), timeout=2)
        try:
            replies = []
            for line in (b"V\r", b"S6\r", b"t70512\r", b"O\r", b"t7051\r", b"Q\r", b"t7050\r"):
                raw.sendall(line)
                replies.append(raw.recv(64))
            assert replies[0] == b"V1013\r" and replies[1] == b"\r"
            assert replies[2] == b"\a"  # a frame before open
            assert replies[3] == b"\r" and replies[4] == b"\a" and replies[5] == b"\a"
            assert replies[6].startswith(b"z\r")
        finally:
            raw.close()
    finally:
        bus.shutdown()
        internal.shutdown()
        srv.close()
