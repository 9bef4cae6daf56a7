"""Emulated programmable DC supply: the supply model and its SCPI server on TCP (loopback).

Clients use a pyserial `socket://127.0.0.1:PORT` URL. Lines end with \\n; several commands may be
joined with ';'. Keywords are case-insensitive and accept SCPI short and long forms
(VOLT/VOLTage, OUTP/OUTPut, MEAS/MEASure, optional SOUR/SOURce root). Commands:

    *IDN?               -> ripplecal,emulated-supply,0,0.1
    *RST, *CLS          reset (output off, scenario voltage) / clear the error queue
    *OPC?               -> 1
    VOLT <v>            setpoint in V, 0..60 (else error -222 queued); no reply
    VOLT?               -> setpoint
    MEAS:VOLT?          -> actual output voltage: 0 with the output off, else setpoint + ~1 mV noise
                           (under a drift fault: the drifted voltage + noise)
    OUTP ON|OFF|1|0     output switch; no reply (OUTP ON while the protection is tripped: -221
                        "Settings conflict" queued, the output stays off)
    OUTP?               -> 1 / 0
    SYST:ERR?           -> oldest queued error, or 0,"No error"

As with real instruments, a command never gets a reply and errors go to the error queue; an unknown
query queues -113 "Undefined header" and gets no reply.

Faults (the emulator's control socket, plant_emulator/faults.py; not reachable over SCPI, and *RST
does not clear them, as a reset command does not repair a supply):
- `drift_to(v)`: the output no longer follows the setpoint: with the output on, the DC link and
  MEAS:VOLT? are at v (a step) while VOLT? still reads the setpoint;
- `trip_output()`: the output protection trips: the output drops to 0 V, OUTP? reads 0, and OUTP ON is
  refused until the fault is cleared;
- `clear_faults()`: both gone; the output follows the setpoint again, and a tripped output stays off
  until OUTP ON (a tripped supply does not switch itself back on).
"""

from __future__ import annotations

import logging
import random
import re
import threading
from collections import deque

from .tcp_server import TcpServer

log = logging.getLogger(__name__)

IDN = "ripplecal,emulated-supply,0,0.1"
MAX_VOLTAGE_V = 60.0
MAX_LINE_BYTES = 1024
ERROR_QUEUE_LEN = 16


class DcSupply:
    """The supply itself. Output starts OFF at the scenario's voltage."""

    def __init__(self, voltage_v: float, noise_v: float = 1e-3, seed: int | None = 0):
        self._initial_v = float(voltage_v)
        self._lock = threading.Lock()
        self.setpoint_v = float(voltage_v)
        self.output_on = False
        self.drift_v: float | None = None  # fault: the output sits here instead of at the setpoint
        self.tripped = False  # fault: output protection tripped (output held off)
        self._noise_v = noise_v
        self._rng = random.Random(seed)
        self.errors: deque[str] = deque(maxlen=ERROR_QUEUE_LEN)

    def _output_v(self) -> float:
        """What the output terminals carry (the caller holds the lock)."""
        if not self.output_on:
            return 0.0
        return self.setpoint_v if self.drift_v is None else self.drift_v

    def actual_v(self) -> float:
        """Voltage at the DC link as the physics sees it (no noise: the DC link is filtered)."""
        with self._lock:
            return self._output_v()

    def measured_v(self) -> float:
        with self._lock:
            if not self.output_on:
                return 0.0
            return max(0.0, self._output_v() + self._rng.gauss(0.0, self._noise_v))

    def reset(self) -> None:
        """*RST: setpoint and output switch to their power-on state (faults stay: see the module doc)."""
        with self._lock:
            self.setpoint_v = self._initial_v
            self.output_on = False

    def set_voltage(self, v: float) -> None:
        with self._lock:
            self.setpoint_v = v

    def set_output(self, on: bool) -> bool:
        """Switch the output; False (nothing changed) for ON while the protection is tripped."""
        with self._lock:
            if on and self.tripped:
                return False
            self.output_on = on
            return True

    # -- faults (control socket) ------------------------------------------------------------------
    def drift_to(self, v: float) -> None:
        """The output drifts to v (with the output on) while the setpoint stays."""
        if not 0.0 <= v <= MAX_VOLTAGE_V:
            raise ValueError(f"volts must be within 0..{MAX_VOLTAGE_V:g}")
        with self._lock:
            self.drift_v = float(v)

    def trip_output(self) -> None:
        """The output protection trips: output off (0 V) and held off until clear_faults()."""
        with self._lock:
            self.tripped = True
            self.output_on = False

    def clear_faults(self) -> None:
        with self._lock:
            self.drift_v = None
            self.tripped = False

    def snapshot(self) -> dict:
        """The supply's state for the control socket's status."""
        with self._lock:
            return {
                "setpoint_v": self.setpoint_v,
                "output_on": self.output_on,
                "actual_v": self._output_v(),
                "drift_v": self.drift_v,
                "tripped": self.tripped,
            }

    # -- SCPI ---------------------------------------------------------------------------------------
    def handle_line(self, line: str) -> list[str]:
        """Execute one line (';'-separated commands). Returns the reply lines (queries only)."""
        replies = []
        for command in line.split(";"):
            command = command.strip()
            if command:
                reply = self._execute(command)
                if reply is not None:
                    replies.append(reply)
        return replies

    def _error(self, code: int, text: str) -> None:
        self.errors.append(f'{code},"{text}"')

    def _execute(self, command: str) -> str | None:
        header, _, arg = command.partition(" ")
        arg = arg.strip()
        h = header.upper()
        is_query = h.endswith("?")
        if h == "*IDN?":
            return IDN
        if h == "*OPC?":
            return "1"
        if h == "*RST":
            self.reset()
            return None
        if h == "*CLS":
            self.errors.clear()
            return None
        if _match(h, r"(SYST(EM)?:)ERR(OR)?(:NEXT)?\?"):
            return self.errors.popleft() if self.errors else '0,"No error"'
        if _match(h, r"((SOUR(CE)?:)?VOLT(AGE)?(:LEV(EL)?)?(:IMM(EDIATE)?)?(:AMPL(ITUDE)?)?)\?"):
            return f"{self.setpoint_v:.4f}"
        if _match(h, r"(SOUR(CE)?:)?VOLT(AGE)?(:LEV(EL)?)?(:IMM(EDIATE)?)?(:AMPL(ITUDE)?)?"):
            try:
                v = float(arg)
            except ValueError:
                self._error(-104, "Data type error")
                return None
            if not 0.0 <= v <= MAX_VOLTAGE_V:
                self._error(-222, "Data out of range")
                return None
            self.set_voltage(v)
            return None
        if _match(h, r"MEAS(URE)?(:SCAL(AR)?)?:VOLT(AGE)?(:DC)?\?"):
            return f"{self.measured_v():.4f}"
        if _match(h, r"OUTP(UT)?(:STAT(E)?)?\?"):
            return "1" if self.output_on else "0"
        if _match(h, r"OUTP(UT)?(:STAT(E)?)?"):
            a = arg.upper()
            if a in ("ON", "1"):
                if not self.set_output(True):
                    self._error(-221, "Settings conflict; output protection tripped")
            elif a in ("OFF", "0"):
                self.set_output(False)
            else:
                self._error(-224, "Illegal parameter value")
            return None
        self._error(-113, f"Undefined header; {command[:40]}")
        log.info("SCPI: unknown %s %r", "query" if is_query else "command", command)
        return None


def _match(header: str, pattern: str) -> bool:
    return re.fullmatch(pattern, header) is not None


class ScpiServer(TcpServer):
    """Line-based SCPI over TCP for one DcSupply; any number of clients, one thread."""

    max_line_bytes = MAX_LINE_BYTES
    log = log

    def __init__(self, supply: DcSupply, host: str = "127.0.0.1", port: int = 0):
        super().__init__("scpi-supply", host=host, port=port)
        self.supply = supply

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def handle_line(self, sock, line: bytes) -> None:
        replies = self.supply.handle_line(line.decode("ascii", errors="replace").strip("\r "))
        if replies:
            self.send(sock, "\n".join(replies) + "\n")
