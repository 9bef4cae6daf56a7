"""Real peers for the driver tests: the other end of each wire, built from the same parts.

- EmulatedDevice: one of the emulator's own CiA 402 devices (plant_emulator's DriveFirmware or
  LoadMachineFirmware: canopen LocalNodes from the same EDS the client reads, walking
  drivers.cia402.DEVICE_TRANSITIONS) on its own python-can `virtual` bus instance, so client and
  server form a symmetric pair (as in canopen's test/test_local.py) and the driver tests meet the
  device the emulated bench runs.
- ScpiPeer: a tiny SCPI instrument on a 127.0.0.1 TCP socket (pyserial URL socket://127.0.0.1:PORT).
"""

from __future__ import annotations

import socket
import threading
import uuid
from pathlib import Path

import can
import canopen

from plant_emulator.cia402_device import Cia402Device


def unique_channel(prefix: str = "ripplecal-test") -> str:
    """A virtual CAN channel name no other test shares (virtual buses with one name are one bus)."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


class EmulatedDevice:
    """An emulator device class (a Cia402Device subclass) booted on a virtual bus of its own.

    device: the emulator's device object (state, stored(), publish(), fault(), ...).
    writes: every SDO write the device accepted, as (index, subindex, value decoded per the EDS), in
    order: a write callback added after the device's own, which raises SdoAbortedError on a refusal
    before this one runs.
    """

    def __init__(self, device_class: type[Cia402Device], channel: str, node_id: int, eds_path: Path, **kwargs):
        self.network = canopen.Network(can.Bus(interface="virtual", channel=channel))
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect()
        self.device = device_class(self.network, node_id, str(eds_path), **kwargs)
        self.node = self.device.node
        self.writes: list[tuple[int, int, object]] = []
        self.lock = threading.Lock()
        self.node.add_write_callback(self._record)
        self.device.boot()

    def _record(self, index: int, subindex: int, od, data: bytes, **_kwargs) -> None:
        with self.lock:
            self.writes.append((index, subindex, od.decode_raw(data)))

    def writes_to(self, index: int, subindex: int = 0) -> list:
        with self.lock:
            return [v for (i, s, v) in self.writes if (i, s) == (index, subindex)]

    def close(self) -> None:
        self.device.shutdown()
        self.network.disconnect()


class ScpiPeer:
    """A SCPI DC supply on 127.0.0.1: answers *IDN?, VOLT?, MEAS:VOLT?, takes VOLT <v> and OUTP ON|OFF.

    silent=True: accepts the connection and every command but never answers (for timeout tests).
    """

    IDN = "ripplecal,TestSupply,0001,1.0"

    def __init__(self, silent: bool = False, max_voltage_v: float = 60.0):
        self.silent = silent
        self.max_voltage_v = max_voltage_v
        self.voltage_setpoint_v = 0.0
        self.output_on = False
        self.commands: list[str] = []
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(0.1)
        self.port = self._server.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="scpi-peer", daemon=True)
        self._thread.start()

    def _reply(self, line: str) -> str | None:
        command = line.strip()
        upper = command.upper()
        self.commands.append(command)
        if upper == "*IDN?":
            return self.IDN
        if upper in ("VOLT?", "SOUR:VOLT?"):
            return f"{self.voltage_setpoint_v:.4f}"
        if upper in ("MEAS:VOLT?", "MEAS:VOLT:DC?"):
            return f"{self.voltage_setpoint_v if self.output_on else 0.0:.4f}"
        if upper.startswith("VOLT "):
            self.voltage_setpoint_v = min(float(command.split()[1]), self.max_voltage_v)
            return None
        if upper in ("OUTP ON", "OUTP 1"):
            self.output_on = True
            return None
        if upper in ("OUTP OFF", "OUTP 0"):
            self.output_on = False
            return None
        return None

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(0.1)
                buf = b""
                while not self._stop.is_set():
                    try:
                        data = conn.recv(4096)
                    except socket.timeout:
                        continue
                    except OSError:
                        break
                    if not data:
                        break
                    buf += data
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        reply = self._reply(line.decode("ascii"))
                        if reply is not None and not self.silent:
                            conn.sendall(reply.encode("ascii") + b"\n")

    def close(self) -> None:
        self._stop.set()
        self._server.close()
        self._thread.join(2.0)
