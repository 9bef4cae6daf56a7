"""Real peers for the driver tests: the other end of each wire, built from the same parts.

- Cia402Peer: a canopen LocalNode from the same EDS the client reads, on its own python-can `virtual`
  bus instance; its 0x6040 write callback walks drivers.cia402.DEVICE_TRANSITIONS and updates 0x6041,
  so client and server form a symmetric pair (as in canopen's test/test_local.py).
- ScpiPeer: a tiny SCPI instrument on a 127.0.0.1 TCP socket (pyserial URL socket://127.0.0.1:PORT).
"""
from __future__ import annotations

import socket
import struct
import threading
import uuid
import zlib
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError

from drivers.cia402 import DEVICE_TRANSITIONS, State402, decode_controlword, decode_statusword, encode_statusword

ABORT_VALUE_RANGE_EXCEEDED = 0x06090030


def unique_channel(prefix: str = "ripplecal-test") -> str:
    """A virtual CAN channel name no other test shares (virtual buses with one name are one bus)."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


class Cia402Peer:
    """A CiA 402 device as a canopen LocalNode on a virtual bus.

    writes: every SDO write the device accepted, as (index, subindex, value decoded per the EDS),
    in order. The torque limit of the drive EDS (+-1000 per mille) is enforced with an SDO abort.
    """

    def __init__(self, channel: str, node_id: int, eds_path: Path, heartbeat_ms: int | None = None):
        self.node_id = node_id
        self.network = canopen.Network(can.Bus(interface="virtual", channel=channel))
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect()
        self.node = canopen.LocalNode(node_id, str(eds_path))
        self.network.add_node(self.node)
        self.writes: list[tuple[int, int, object]] = []
        self.commits = 0
        self.lock = threading.Lock()
        self.set_statusword(State402.SWITCH_ON_DISABLED)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        if heartbeat_ms is not None:
            self.node.data_store.setdefault(0x1017, {})[0] = struct.pack("<H", heartbeat_ms)
        # INITIALISING -> PRE-OPERATIONAL starts the heartbeat producer with 0x1017 (NmtSlave)
        self.node.nmt.state = "PRE-OPERATIONAL"

    # -- object dictionary access -------------------------------------------------------------------
    def set_value(self, index: int, subindex: int, value) -> None:
        """Set an object the way the device firmware would (no write callbacks, not recorded)."""
        od = self.node.object_dictionary.get_variable(index, subindex)
        self.node.data_store.setdefault(index, {})[subindex] = od.encode_raw(value)

    def value(self, index: int, subindex: int = 0):
        od = self.node.object_dictionary.get_variable(index, subindex)
        return od.decode_raw(self.node.get_data(index, subindex))

    def set_statusword(self, state: State402) -> None:
        self.set_value(0x6041, 0, encode_statusword(state))

    @property
    def state(self) -> State402:
        return decode_statusword(self.value(0x6041))

    def writes_to(self, index: int, subindex: int = 0) -> list:
        with self.lock:
            return [v for (i, s, v) in self.writes if (i, s) == (index, subindex)]

    # -- device behaviour ---------------------------------------------------------------------------
    def _on_write(self, index: int, subindex: int, od, data: bytes, **_kwargs) -> None:
        value = od.decode_raw(data)
        if index == 0x6071 and not -1000 <= value <= 1000:
            raise SdoAbortedError(ABORT_VALUE_RANGE_EXCEEDED)
        with self.lock:
            self.writes.append((index, subindex, value))
        if index == 0x6040:
            command = decode_controlword(value)
            if command is not None:
                new_state = DEVICE_TRANSITIONS.get((self.state, command))
                if new_state is not None:
                    self.set_statusword(new_state)
        elif index == 0x2001 and subindex == 1:
            self.set_value(0x2001, 2, zlib.crc32(bytes(data)) & 0xFFFFFFFF)
            self.set_value(0x2001, 3, 1)
        elif index == 0x2000 and subindex == 7 and value == 1:
            with self.lock:
                self.commits += 1

    def _on_read(self, index: int, subindex: int, od, **_kwargs):
        if index == 0x2000 and subindex == 7:
            return self.commits % 256
        return None

    def stop_heartbeat(self) -> None:
        self.node.nmt.stop_heartbeat()

    def close(self) -> None:
        self.node.nmt.stop_heartbeat()
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
