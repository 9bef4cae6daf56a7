"""The bench's oscilloscope: records per-sample signals the service cannot see through its wires.

A real bench has a scope or the drive's own trace buffer on u_dq*, i_dq; the emulator offers the
same on its control socket (plant_emulator/faults.py), for tools such as the paper report
(`ripplecal paper`). The service's identification never reads it.

Protocol (control socket, JSON lines):
    {"scope": "arm", "samples": N}   record the next N control periods (1..MAX_SAMPLES) from the
                                     next physics block on; a new arm discards an old record
    {"scope": "read"}                {"ok": true, "ready": false, "recorded": n} while recording,
                                     then {"ok": true, "ready": true, "sample_rate_hz": f,
                                     "channels": {name: [values]}} (SI units, names in CHANNELS)
"""

from __future__ import annotations

import threading

import numpy as np

from . import physics as ph

MAX_SAMPLES = 65536  # 4 s at 16 kHz; one reply line of a few MB at most

# channel name (unit in the suffix) -> column of the physics trace
CHANNELS = {
    "i_d_a": ph.TR_ID,
    "i_q_a": ph.TR_IQ,
    "u_d_v": ph.TR_UD,
    "u_q_v": ph.TR_UQ,  # nominal control output u_dq
    "u_d_star_v": ph.TR_UD_STAR,
    "u_q_star_v": ph.TR_UQ_STAR,  # after injection: what the inverter is told
    "torque_nm": ph.TR_TORQUE,
    "disturbance_nm": ph.TR_DIST,
    "alpha_rad_s2": ph.TR_ALPHA_MEAS,
    "phi_e_rad": ph.TR_PHI_E,
    "v_inj_rad": ph.TR_V_INJ,
}


class Scope:
    """Armed from the control socket's thread, fed by the plant thread (one lock between them)."""

    def __init__(self, sample_rate_hz: float):
        self.sample_rate_hz = float(sample_rate_hz)
        self._lock = threading.Lock()
        self._wanted = 0
        self._rows: list[np.ndarray] = []
        self._recorded = 0

    def arm(self, samples: int) -> None:
        if not 1 <= samples <= MAX_SAMPLES:
            raise ValueError(f"samples must be within 1..{MAX_SAMPLES}")
        with self._lock:
            self._wanted, self._rows, self._recorded = samples, [], 0

    @property
    def recording(self) -> bool:
        """True while samples are still wanted (the plant thread then records a trace)."""
        return self._recorded < self._wanted

    def feed(self, trace: np.ndarray) -> None:
        """Rows of a physics trace (n, N_TRACE) just simulated; keeps what the record still needs."""
        with self._lock:
            need = self._wanted - self._recorded
            if need <= 0:
                return
            rows = trace[:need].copy()
            self._rows.append(rows)
            self._recorded += len(rows)

    def read(self) -> dict:
        with self._lock:
            if self._wanted == 0:
                raise ValueError("the scope is not armed")
            if self._recorded < self._wanted:
                return {"ok": True, "ready": False, "recorded": self._recorded, "samples": self._wanted}
            data = np.concatenate(self._rows)
        return {
            "ok": True,
            "ready": True,
            "sample_rate_hz": self.sample_rate_hz,
            "samples": len(data),
            "channels": {name: np.round(data[:, col], 7).tolist() for name, col in CHANNELS.items()},
        }

    def command(self, cmd: dict) -> dict:
        action = cmd.get("scope")
        if action == "arm":
            self.arm(int(cmd["samples"]))
            return {"ok": True}
        if action == "read":
            return self.read()
        raise ValueError(f"unknown scope command {action!r} (arm, read)")
