"""The emulated bench's oscilloscope, read over the emulator's control socket (plant_emulator/scope.py).

Only the paper report uses it, for the signals a test bench shows on a scope and the service cannot
see through its wires (u_dq*, i_dq). The identification never reads it: every gamma, delta and
suppression figure of the report is the service's own measurement on the DAQ.
"""

from __future__ import annotations

import json
import math
import socket
import time
from dataclasses import dataclass

import numpy as np

READ_POLL_S = 0.05


class ScopeError(RuntimeError):
    pass


@dataclass
class Trace:
    """One scope record: channels in SI units (names as plant_emulator.scope.CHANNELS), one sample per control period."""

    sample_rate_hz: float
    channels: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.channels[name]

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(len(self.channels["phi_e_rad"])) / self.sample_rate_hz

    @property
    def u_star_magnitude_v(self) -> np.ndarray:
        """|u_dq*|, the voltage the inverter is told (after injection)."""
        return np.hypot(self["u_d_star_v"], self["u_q_star_v"])

    def harmonic_amplitude(self, name: str, order: int) -> float:
        """Amplitude of the `order`-th electrical harmonic of a channel: least squares of
        x = c0 + a cos(h phi_e) + b sin(h phi_e), amplitude sqrt(a^2 + b^2) (unbiased on any record
        length, unlike a plain DFT over a non-integer number of periods)."""
        phi = self["phi_e_rad"]
        basis = np.column_stack([np.ones_like(phi), np.cos(order * phi), np.sin(order * phi)])
        coef, *_ = np.linalg.lstsq(basis, self[name], rcond=None)
        return float(math.hypot(coef[1], coef[2]))


class Scope:
    """Client of the control socket's scope commands (JSON lines, one reply line each)."""

    def __init__(self, control_url: str, timeout_s: float = 10.0):
        host, port = control_url.removeprefix("tcp://").rsplit(":", 1)
        self.address = (host, int(port))
        self.timeout_s = timeout_s

    def _command(self, cmd: dict) -> dict:
        with socket.create_connection(self.address, timeout=self.timeout_s) as sock:
            sock.sendall((json.dumps(cmd) + "\n").encode("ascii"))
            with sock.makefile("r", encoding="ascii") as reader:
                line = reader.readline()
        if not line:
            raise ScopeError("the emulator's control socket closed without a reply")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise ScopeError(f"scope command {cmd!r} refused: {reply.get('error')}")
        return reply

    def arm(self, samples: int) -> None:
        self._command({"scope": "arm", "samples": int(samples)})

    def read(self, advance, timeout_s: float = 30.0) -> Trace:
        """The armed record once it is complete. `advance()` lets plant time pass (a DAQ window: the
        emulator runs only as fast as the DAQ is read); it is called between polls."""
        deadline = time.monotonic() + timeout_s
        while True:
            reply = self._command({"scope": "read"})
            if reply["ready"]:
                return Trace(
                    float(reply["sample_rate_hz"]),
                    {k: np.asarray(v, dtype=float) for k, v in reply["channels"].items()},
                )
            if time.monotonic() > deadline:
                raise ScopeError(
                    f"scope record not complete within {timeout_s:g} s "
                    f"({reply['recorded']} of {reply['samples']} samples)"
                )
            advance()
            time.sleep(READ_POLL_S)
