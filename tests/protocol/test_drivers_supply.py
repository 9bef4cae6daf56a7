"""ScpiSupply against a small SCPI peer on a loopback TCP socket (pyserial URL socket://127.0.0.1:PORT),
and against the emulator's own supply with its faults."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from drivers.dc_supply import ScpiSupply
from drivers.errors import ScpiError, ScpiTimeout
from plant_emulator.scpi_supply import IDN, DcSupply, ScpiServer
from tests.support.drivers_peers import ScpiPeer
from tests.support.waiting import wait_until


@pytest.fixture
def peer():
    server = ScpiPeer()
    yield server
    server.close()


def test_identify_set_and_read_voltage_and_output(peer):
    with ScpiSupply(peer.url, timeout_s=1.0) as supply:
        assert supply.identify() == ScpiPeer.IDN
        assert supply.set_voltage(12.5) == pytest.approx(12.5)
        assert supply.voltage_setpoint() == pytest.approx(12.5)
        assert supply.measure_voltage() == pytest.approx(0.0)  # output still off
        supply.output(True)
        assert supply.measure_voltage() == pytest.approx(12.5)
        supply.output(False)
        assert supply.measure_voltage() == pytest.approx(0.0)
    assert peer.commands == [
        "*IDN?",
        "VOLT 12.5",
        "VOLT?",
        "VOLT?",
        "MEAS:VOLT?",
        "OUTP ON",
        "MEAS:VOLT?",
        "OUTP OFF",
        "MEAS:VOLT?",
    ]


def test_setpoint_the_supply_did_not_take_is_an_error():
    server = ScpiPeer(max_voltage_v=30.0)
    try:
        with ScpiSupply(server.url) as supply:
            with pytest.raises(ScpiError, match="read back as 30 V after 'VOLT 48'"):
                supply.set_voltage(48.0)
            with pytest.raises(ValueError):
                supply.set_voltage(-1.0)
    finally:
        server.close()


def test_silent_peer_times_out_with_a_clear_error():
    server = ScpiPeer(silent=True)
    try:
        with ScpiSupply(server.url, timeout_s=0.3) as supply:
            t0 = time.monotonic()
            with pytest.raises(ScpiTimeout, match=r"no reply to 'MEAS:VOLT\?' within 0.3 s"):
                supply.measure_voltage()
            assert 0.25 < time.monotonic() - t0 < 5.0
            supply.output(True)  # commands without a reply still go out
        assert wait_until(lambda: "OUTP ON" in server.commands, 10.0)
    finally:
        server.close()


def test_garbled_reply_is_an_error():
    """A peer that answers with something that is not a number (wrong instrument, wrong baud rate)."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve():
        conn, _ = server.accept()
        with conn:
            conn.settimeout(2.0)
            try:
                while conn.recv(256):
                    conn.sendall(b"\xff\xfeOK?\n")
            except OSError:
                pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        with ScpiSupply(f"socket://127.0.0.1:{port}", timeout_s=0.5) as supply:
            time.sleep(0.1)
            with pytest.raises(ScpiError, match=r"garbled reply to 'VOLT\?'"):
                supply.voltage_setpoint()
    finally:
        server.close()
        thread.join(3.0)


def test_the_emulated_supply_drifting_and_tripping_as_the_driver_sees_it():
    """The emulator's own SCPI supply (plant_emulator/scpi_supply.py) under its control-socket faults:
    what the service's supply interlock reads (MEAS:VOLT?) moves, the setpoint (VOLT?) stays."""
    emulated = DcSupply(12.0, seed=1)
    server = ScpiServer(emulated).start()
    try:
        with ScpiSupply(server.url, timeout_s=2.0) as supply:
            assert supply.identify() == IDN
            supply.set_voltage(12.0)
            supply.output(True)
            assert supply.measure_voltage() == pytest.approx(12.0, abs=0.01)
            emulated.drift_to(9.0)
            assert supply.measure_voltage() == pytest.approx(9.0, abs=0.01)
            assert supply.voltage_setpoint() == pytest.approx(12.0)
            emulated.trip_output()
            assert supply.measure_voltage() == 0.0 and supply.query("OUTP?") == "0"
            supply.output(True)  # refused while tripped: the output stays off
            assert supply.measure_voltage() == 0.0
            assert supply.query("SYST:ERR?").startswith("-221")
            emulated.clear_faults()
            assert supply.measure_voltage() == 0.0  # a tripped output stays off ...
            supply.output(True)  # ... until switched on again
            assert supply.measure_voltage() == pytest.approx(12.0, abs=0.01)
    finally:
        server.close()
