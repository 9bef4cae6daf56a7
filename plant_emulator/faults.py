"""Fault hooks for reliability work: DAQ byte drops / corruption / disconnect, drive heartbeat stop,
EMCY from the drive, delayed SDO responses, DC supply drift and trip. Switchable by the scenario
([faults]) or at run time on a loopback control socket (`"control": "tcp://127.0.0.1:P"` in the endpoints JSON).

Control protocol: JSON lines; each command gets one reply line, `{"ok": true, ...}` or
`{"ok": false, "error": "..."}`. Commands:

    {"fault": "daq_drop_bytes", "rate": 0.001}   each DAQ byte is dropped with this probability
    {"fault": "daq_corrupt", "rate": 0.001}      each DAQ byte gets one random bit flipped with it
    {"fault": "daq_disconnect"}                  the DAQ port hangs up (readers get EOF/EIO); frames
                                                 produced meanwhile are lost
    {"fault": "daq_reconnect"}                   a new DAQ pty behind the same stable path; the reply names
                                                 both: {"ok": true, "daq": "<link>", "device": "/dev/pts/N"}
    {"fault": "heartbeat_stop"}                  the drive stops producing its heartbeat ("node": 6 for the load)
    {"fault": "emcy", "code": 12816}             the drive sends this EMCY and goes to FAULT
                                                 ("fault_state": false: EMCY only; "node": 6 for the load)
    {"fault": "sdo_delay", "seconds": 1.0}       every SDO response of the emulator is held this long
    {"fault": "supply_voltage", "volts": 9.0}    the DC supply's output drifts to this voltage (0..60 V, a
                                                 step): MEAS:VOLT? and the physics' DC link (the drive's
                                                 0x6079) show it while the output is on; VOLT? still reads
                                                 the setpoint
    {"fault": "supply_output_off"}               the supply trips: its output drops to 0 V (OUTP? reads 0,
                                                 MEAS:VOLT? 0, the drive's power stage has no DC link:
                                                 drive_firmware.py's udc_min_v) and OUTP ON is refused
                                                 (SCPI error -221) until clear
    {"fault": "miswire", "what": "angle_reversed"}   the bench wired wrong, for the bring-up check: angle_reversed
                                                 (the encoder counts backwards), sync_absent (the sync line
                                                 not wired: its flag never set), accel_disconnected (the
                                                 accelerometer's input reads 0); "on": false undoes one
    {"fault": "clear"}                           rates 0, SDO delay 0, heartbeats produced again, the
                                                 supply's output follows its setpoint again (a tripped
                                                 output stays off until OUTP ON, as on a real supply; a
                                                 disconnected DAQ needs daq_reconnect)
    {"scope": "arm", "samples": N}, {"scope": "read"}
                                                 the bench's oscilloscope on u_dq*, i_dq, ... (plant_emulator/scope.py)
    {"status": true}                             the fault state: {"ok": true, "faults": {...}}, with the
                                                 drive's state, injection mode and torque setpoint in force,
                                                 `drive_power_off_at` (time.monotonic() when its power
                                                 stage last went off), the load's state, each
                                                 device's heartbeat consumer time (0x1016, ms; 0: off),
                                                 `supply` {setpoint_v, output_on, actual_v, drift_v,
                                                 tripped}, `plant_samples` (the plant time simulated so
                                                 far, in DAQ samples) and `daq_frames_dropped` (frames
                                                 the DAQ could not deliver: nobody read, see process.py)

Every reply carries `"at"`: time.monotonic() just before the command was carried out (CLOCK_MONOTONIC is
system-wide, so a tool in another process can time fault -> safe against `drive_power_off_at`).

The service never uses this socket; tests, reliability tools and the paper report (its scope) do. Only 127.0.0.1, ever.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import numpy as np

from drivers.daq_protocol import CRC_FIRST, CRC_STOP, FLAG_SYNC_INPUT, FRAME_BYTES, crc16_rows

from .tcp_server import TcpServer

log = logging.getLogger(__name__)

MAX_LINE_BYTES = 4096
MISWIRINGS = ("angle_reversed", "sync_absent", "accel_disconnected")


class FaultState:
    """Current fault switches and the actions behind them (bound to the emulator's parts)."""

    def __init__(self, emulator, config: dict | None = None, seed: int | None = None):
        self.emu = emulator
        self.lock = threading.Lock()
        self.rng = np.random.default_rng(seed)
        self.drop_rate = 0.0
        self.corrupt_rate = 0.0
        self.sdo_delay_s = 0.0
        self.heartbeat_stopped: set[int] = set()
        self.daq_disconnected = False
        self.bytes_dropped = 0
        self.bytes_corrupted = 0
        self.events: list[dict] = []
        self.miswired: set[str] = set()  # MISWIRINGS in force (the bring-up check's cases)
        config = config or {}
        self.drop_rate = float(config.get("daq_drop_bytes_rate", 0.0))
        self.corrupt_rate = float(config.get("daq_corrupt_rate", 0.0))
        self.sdo_delay_s = float(config.get("sdo_delay_s", 0.0))
        for ev in config.get("events", []) or []:
            if "at_s" not in ev or "fault" not in ev:
                raise ValueError(f"[faults] events entries need at_s and fault: {ev!r}")
            self.events.append(dict(ev))
        self.events.sort(key=lambda e: float(e["at_s"]))

    # -- plant thread ------------------------------------------------------------------------------
    def tick(self, plant_time_s: float) -> None:
        """Run the scenario's timed events that are due."""
        while self.events and float(self.events[0]["at_s"]) <= plant_time_s:
            ev = self.events.pop(0)
            reply = self.command({k: v for k, v in ev.items() if k != "at_s"})
            log.info("timed fault %r at %.3f s: %r", ev, plant_time_s, reply)

    def miswire(self, frames: np.ndarray) -> None:
        """The DAQ frames (FRAME_DTYPE, in place) as a mis-wired bench delivers them (`miswired`), CRC made again:
        the wire is fine, the wiring is not."""
        wrong = self.miswired
        if not wrong:
            return
        if "angle_reversed" in wrong:
            frames["angle"] = (-frames["angle"].astype(np.int64)) & 0xFFFF
        if "sync_absent" in wrong:
            frames["flags"] &= ~np.uint16(FLAG_SYNC_INPUT)
        if "accel_disconnected" in wrong:
            frames["accel"] = 0
        raw = frames.view(np.uint8).reshape(len(frames), FRAME_BYTES)
        frames["crc"] = crc16_rows(raw[:, CRC_FIRST:CRC_STOP])

    def apply_daq(self, data: bytes) -> bytes:
        """The DAQ bytes as the wire delivers them under the current drop/corrupt rates."""
        drop, corrupt = self.drop_rate, self.corrupt_rate
        if drop <= 0.0 and corrupt <= 0.0:
            return data
        buf = np.frombuffer(data, dtype=np.uint8).copy()
        n = len(buf)
        if corrupt > 0.0:
            k = int(self.rng.binomial(n, min(corrupt, 1.0)))
            if k:
                pos = self.rng.integers(0, n, size=k)
                buf[pos] ^= np.uint8(1) << self.rng.integers(0, 8, size=k).astype(np.uint8)
                self.bytes_corrupted += k
        if drop > 0.0:
            k = int(self.rng.binomial(n, min(drop, 1.0)))
            if k:
                keep = np.ones(n, dtype=bool)
                keep[self.rng.integers(0, n, size=k)] = False
                self.bytes_dropped += int(n - keep.sum())
                buf = buf[keep]
        return buf.tobytes()

    # -- commands ----------------------------------------------------------------------------------
    def command(self, cmd: dict) -> dict:
        at = time.monotonic()  # before the fault acts: fault -> safe is timed from here
        try:
            reply = self._command(cmd)
        except (KeyError, TypeError, ValueError) as exc:
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        reply["at"] = at
        return reply

    def _node(self, cmd: dict):
        node = int(cmd.get("node", self.emu.drive.node.id))
        for dev in (self.emu.drive, self.emu.load):
            if dev.node.id == node:
                return dev
        raise ValueError(f"no node {node}")

    def _command(self, cmd: dict) -> dict:
        if not isinstance(cmd, dict):
            raise TypeError("a command is a JSON object")
        if cmd.get("status"):
            return {"ok": True, "faults": self.snapshot()}
        if "scope" in cmd:
            return self.emu.scope.command(cmd)
        fault = cmd.get("fault")
        if fault == "daq_drop_bytes":
            self.drop_rate = _rate(cmd)
        elif fault == "daq_corrupt":
            self.corrupt_rate = _rate(cmd)
        elif fault == "daq_disconnect":
            self.daq_disconnected = True
            self.emu.daq.hang_up()
        elif fault == "daq_reconnect":
            name = self.emu.daq.reopen()
            self.daq_disconnected = False
            return {"ok": True, "daq": self.emu.daq.link, "device": name}
        elif fault == "heartbeat_stop":
            dev = self._node(cmd)
            self.heartbeat_stopped.add(dev.node.id)
            dev.node.nmt.stop_heartbeat()
        elif fault == "emcy":
            dev = self._node(cmd)
            code = int(cmd["code"])
            if not 0 <= code <= 0xFFFF:
                raise ValueError("code must be 0..65535")
            if cmd.get("fault_state", True):
                dev.fault(code)
            else:
                dev.node.emcy.send(code, 0x01)
        elif fault == "sdo_delay":
            seconds = float(cmd["seconds"])
            if not 0.0 <= seconds <= 60.0:
                raise ValueError("seconds must be within 0..60")
            self.sdo_delay_s = seconds
        elif fault == "supply_voltage":
            self.emu.supply.drift_to(float(cmd["volts"]))
        elif fault == "supply_output_off":
            self.emu.supply.trip_output()
        elif fault == "miswire":
            what = str(cmd.get("what"))
            if what not in MISWIRINGS:
                raise ValueError(f"miswire what {what!r}: one of {', '.join(MISWIRINGS)}")
            if cmd.get("on", True):
                self.miswired.add(what)
            else:
                self.miswired.discard(what)
        elif fault == "clear":
            self.miswired.clear()
            self.drop_rate = self.corrupt_rate = self.sdo_delay_s = 0.0
            self.emu.supply.clear_faults()
            for dev in (self.emu.drive, self.emu.load):
                if dev.node.id in self.heartbeat_stopped:
                    dev.node.nmt.start_heartbeat(int(dev.stored(0x1017)))
            self.heartbeat_stopped.clear()
        else:
            raise ValueError(f"unknown fault {fault!r}")
        return {"ok": True}

    def snapshot(self) -> dict:
        return {
            "daq_drop_bytes_rate": self.drop_rate,
            "daq_corrupt_rate": self.corrupt_rate,
            "sdo_delay_s": self.sdo_delay_s,
            "heartbeat_stopped": sorted(self.heartbeat_stopped),
            "daq_disconnected": self.daq_disconnected,
            "miswired": sorted(self.miswired),
            "bytes_dropped": self.bytes_dropped,
            "bytes_corrupted": self.bytes_corrupted,
            "pending_events": len(self.events),
            "drive_state": self.emu.drive.state.value,
            "drive_power_off_at": self.emu.drive.power_off_at,
            "drive_injection_mode": self.emu.drive.inj_mode,
            "drive_torque_nm": self.emu.drive.torque_nm,
            "drive_theta_rad": list(self.emu.drive.effective_theta()),
            # further orders in force: [[order, theta_cos, theta_sin], ...] (scaled as the control loop takes them)
            "drive_further_theta_rad": [list(f) for f in self.emu.drive.effective_further()],
            "drive_speed_rpm": self.emu.drive.speed_rpm,
            "load_state": self.emu.load.state.value,
            # whose heartbeat each device consumes, and how long it waits (0: it does not)
            "drive_heartbeat_consumer_ms": self.emu.drive.heartbeat_consumer_ms,
            "load_heartbeat_consumer_ms": self.emu.load.heartbeat_consumer_ms,
            "supply": self.emu.supply.snapshot(),
            "plant_samples": self.emu.samples,
            "daq_frames_dropped": self.emu.daq.frames_dropped,
        }

    def sdo_delay_for(self, can_id: int) -> float:
        """Delay for a frame the emulator sends (SDO responses 0x580 + node of its nodes)."""
        if self.sdo_delay_s <= 0.0:
            return 0.0
        if can_id - 0x580 in (self.emu.drive.node.id, self.emu.load.node.id):
            return self.sdo_delay_s
        return 0.0


def _rate(cmd: dict) -> float:
    rate = float(cmd["rate"])
    if not 0.0 <= rate <= 1.0:
        raise ValueError("rate must be within 0..1")
    return rate


class ControlServer(TcpServer):
    """JSON-lines control socket on 127.0.0.1 (port 0: a free one)."""

    max_line_bytes = MAX_LINE_BYTES
    log = log

    def __init__(self, faults: FaultState, port: int = 0):
        super().__init__("control", port=port)
        self.faults = faults

    @property
    def url(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    def handle_line(self, sock, line: bytes) -> None:
        if not line.strip():
            return
        try:
            cmd = json.loads(line)
        except ValueError as exc:
            self._reply_obj(sock, {"ok": False, "error": f"not JSON: {exc}"})
            return
        try:
            reply = self.faults.command(cmd)
        except Exception as exc:  # a broken command must not take the server down
            log.exception("control command %r", cmd)
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        self._reply_obj(sock, reply)

    def line_too_long(self, sock) -> None:
        self._reply_obj(sock, {"ok": False, "error": "line too long"})

    def _reply_obj(self, sock, obj: dict) -> None:
        self.send(sock, json.dumps(obj) + "\n")
