"""Programmable DC supply for the DC-link voltage, SCPI over any pyserial URL.

Only the commands every bench supply understands are used (`*IDN?`, `VOLT <v>`, `VOLT?`,
`MEAS:VOLT?`, `OUTP ON|OFF`). Each query waits for one newline-terminated reply with a timeout, and a
missing or unparsable reply is an error that quotes the command and what came back, so a wrong port or
a supply in local mode is recognisable from the message alone. set_voltage reads the setpoint back:
SCPI has no acknowledge, and a supply that clamps or ignores the value must not pass silently.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import serial

from drivers.errors import ScpiError, ScpiTimeout

TERMINATOR = b"\n"
MAX_REPLY_BYTES = 256


def _no_nagle(port) -> None:
    """A supply on a TCP socket (socket://, e.g. LAN SCPI on port 5025): send each line at once. With
    Nagle's algorithm a query right after a command ('VOLT 12' then 'VOLT?') waits for the supply's
    delayed ACK of the first, ~40 ms. pyserial keeps the socket in `_socket`; other ports have none."""
    sock = getattr(port, "_socket", None)
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class ScpiSupply:
    """SCPI DC supply. url: any pyserial URL (/dev/ttyUSB0, socket://127.0.0.1:5025, loop://)."""

    def __init__(self, url: str, timeout_s: float = 1.0, baudrate: int = 9600, setpoint_tolerance_v: float = 0.01):
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.url = url
        self.timeout_s = timeout_s
        self.setpoint_tolerance_v = setpoint_tolerance_v
        # short per-read timeout; the reply deadline is enforced in _readline
        self._port = serial.serial_for_url(
            url, timeout=min(0.05, timeout_s), write_timeout=timeout_s, baudrate=baudrate
        )
        _no_nagle(self._port)
        self._lock = threading.Lock()
        self._rx = bytearray()

    # -- transport ----------------------------------------------------------------------------------
    def write(self, command: str) -> None:
        """Send one command line (no reply expected)."""
        with self._lock:
            self._send(command)

    def query(self, command: str) -> str:
        """Send one query and return its reply line (stripped)."""
        with self._lock:
            self._discard_stale_input()
            self._send(command)
            return self._readline(command)

    def _send(self, command: str) -> None:
        try:
            self._port.write(command.encode("ascii") + TERMINATOR)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise ScpiError(f"supply {self.url}: sending {command!r} failed: {exc}") from exc

    def _discard_stale_input(self) -> None:
        """Late replies of an earlier, timed-out query must not be taken as this query's answer."""
        self._rx.clear()
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass

    def _readline(self, command: str) -> str:
        deadline = time.monotonic() + self.timeout_s
        while TERMINATOR not in self._rx:
            if time.monotonic() >= deadline:
                got = bytes(self._rx)
                self._rx.clear()
                raise ScpiTimeout(
                    f"supply {self.url}: no reply to {command!r} within {self.timeout_s:g} s"
                    + (f" (partial reply {got!r})" if got else "")
                )
            if len(self._rx) > MAX_REPLY_BYTES:
                got = bytes(self._rx)
                self._rx.clear()
                raise ScpiError(f"supply {self.url}: reply to {command!r} is not a SCPI line: {got[:64]!r}...")
            try:
                waiting = self._port.in_waiting
                data = self._port.read(max(1, min(waiting, MAX_REPLY_BYTES)))
            except (serial.SerialException, OSError) as exc:
                raise ScpiError(f"supply {self.url}: reading the reply to {command!r} failed: {exc}") from exc
            self._rx += data
        line, _, rest = bytes(self._rx).partition(TERMINATOR)
        self._rx[:] = rest
        try:
            return line.decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise ScpiError(f"supply {self.url}: garbled reply to {command!r}: {line!r}") from exc

    def _query_float(self, command: str) -> float:
        reply = self.query(command)
        try:
            value = float(reply)
        except ValueError:
            raise ScpiError(f"supply {self.url}: reply to {command!r} is not a number: {reply!r}") from None
        if not math.isfinite(value) or abs(value) >= 9.9e37:  # 9.91e37 is SCPI's "not a number"
            raise ScpiError(f"supply {self.url}: reply to {command!r} is not a valid value: {reply!r}")
        return value

    # -- instrument ---------------------------------------------------------------------------------
    def identify(self) -> str:
        """`*IDN?`: manufacturer, model, serial, firmware."""
        reply = self.query("*IDN?")
        if not reply:
            raise ScpiError(f"supply {self.url}: empty reply to '*IDN?'")
        return reply

    def set_voltage(self, voltage_v: float) -> float:
        """`VOLT <v>`, then `VOLT?` to check that the supply took it. Returns the read-back setpoint."""
        if not math.isfinite(voltage_v) or voltage_v < 0:
            raise ValueError(f"voltage must be a finite value >= 0 V, got {voltage_v!r}")
        self.write(f"VOLT {voltage_v:.6g}")
        setpoint_v = self.voltage_setpoint()
        if abs(setpoint_v - voltage_v) > max(self.setpoint_tolerance_v, 1e-4 * abs(voltage_v)):
            raise ScpiError(
                f"supply {self.url}: setpoint read back as {setpoint_v:g} V after 'VOLT {voltage_v:.6g}' "
                "(limit, range or local mode?)"
            )
        return setpoint_v

    def voltage_setpoint(self) -> float:
        """`VOLT?`: programmed output voltage, V."""
        return self._query_float("VOLT?")

    def measure_voltage(self) -> float:
        """`MEAS:VOLT?`: measured output voltage, V."""
        return self._query_float("MEAS:VOLT?")

    def output(self, on: bool) -> None:
        """`OUTP ON|OFF`."""
        self.write("OUTP ON" if on else "OUTP OFF")

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> "ScpiSupply":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
