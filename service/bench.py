"""The bench as the service sees it: drive and load machine over CANopen, DAQ, DC supply.

Drivers are chosen by settings strings (CAN interface, pyserial URLs); nothing here knows whether
the bench is emulated. Safety (pymeasure's startup/execute/shutdown): every operating-point run
ends in `make_safe` (torque off, injection off, drive disabled, load stopped), also after an error
or a cancel, and every wait has a timeout.
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from datetime import datetime, timezone
from typing import Any, Iterator

from drivers.canopen_bus import CanBus
from drivers.daq_reader import DaqReader
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient
from drivers.load_machine import LoadClient
from service.demodulation import ResonanceMode, ResonanceTracker
from service.harmonic import mechanical_speed_rpm
from service.measurement import DaqCursor, OperatingPointSession, RunCancelled
from service.operating_point import OperatingPoint
from service.settings import Settings

log = logging.getLogger(__name__)


class BenchError(RuntimeError):
    pass


class LimitError(ValueError):
    """A setpoint outside the bench's safety limits (checked before anything is sent).
    `problems` pairs each operating-point field at fault with what is wrong (the API's 422 names them)."""

    def __init__(self, message: str, problems: tuple[tuple[str, str], ...] = ()):
        super().__init__(message)
        self.problems = problems


def check_limits(op: OperatingPoint, settings: Settings) -> None:
    lim = settings.safety
    problems = []
    for field in ("torque_nm", "speed_rpm", "udc_v"):
        if not math.isfinite(getattr(op, field)):      # NaN compares False with every limit below
            problems.append((field, f"{field} must be a finite number, got {getattr(op, field)}"))
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))
    if abs(op.torque_nm) > lim.max_torque_nm:
        problems.append(("torque_nm", f"torque_nm {op.torque_nm:g} exceeds the limit of {lim.max_torque_nm:g} Nm"))
    if lim.torque_sign == "positive" and op.torque_nm < 0 or lim.torque_sign == "negative" and op.torque_nm > 0:
        problems.append(("torque_nm", f"torque_nm {op.torque_nm:g}: this bench allows {lim.torque_sign} torque only "
                                      f"(safety.torque_sign)"))
    if abs(op.speed_rpm) > lim.max_speed_rpm:
        problems.append(("speed_rpm", f"speed_rpm {op.speed_rpm:g} exceeds the limit of {lim.max_speed_rpm:g} rpm"))
    if abs(op.speed_rpm) < lim.min_speed_rpm:
        problems.append(("speed_rpm", f"speed_rpm {op.speed_rpm:g} is below the minimum of {lim.min_speed_rpm:g} rpm "
                                      f"(safety.min_speed_rpm)"))
    if not lim.min_udc_v <= op.udc_v <= lim.max_udc_v:
        problems.append(("udc_v", f"udc_v {op.udc_v:g} outside {lim.min_udc_v:g}..{lim.max_udc_v:g} V"))
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))


class Bench:
    def __init__(self, settings: Settings, identity: str):
        self.settings = settings
        self.identity = identity
        self._lock = threading.RLock()          # one user of the wires at a time (SDO is not re-entrant)
        self.bus: CanBus | None = None
        self.drive: DriveClient | None = None
        self.load: LoadClient | None = None
        self.daq: DaqReader | None = None
        self.supply: ScpiSupply | None = None
        self.cursor: DaqCursor | None = None
        self.busy = False
        self.cancel_event = None                # set by the engine; checked at every DAQ read
        self._gamma_max_rad: float | None = None  # of the run in progress
        # the shaft mode of G_Salpha: the settings' pole, learned from the windows of every run (sec. 2.3)
        self.resonance = ResonanceTracker(ResonanceMode(settings.mechanics.pole_re_rad_s, settings.mechanics.pole_im_rad_s))
        self._status: dict[str, Any] = {"connected": False, "bench": identity, "busy": False,
                                        "drive": None, "load": None, "daq": None, "updated_at": None, "error": None}

    # --- lifecycle ---------------------------------------------------------------------------------
    def connect(self) -> None:
        s = self.settings
        if not s.daq.url or not s.supply.url:
            raise BenchError("bench settings name no DAQ port (daq.url) or supply port (supply.url)")
        self.bus = CanBus(s.can.interface, s.can.channel, host=s.can.host, port=s.can.port, bitrate=s.can.bitrate,
                          service_node_id=s.can.service_node_id, heartbeat_period_ms=s.can.heartbeat_period_ms)
        self.bus.connect()
        self.drive = DriveClient(self.bus, s.can.drive_node, sdo_timeout_s=s.can.sdo_timeout_s)
        self.drive.connect()
        self.load = LoadClient(self.bus, s.can.load_node, sdo_timeout_s=s.can.sdo_timeout_s)
        self.load.connect()
        self.supply = ScpiSupply(s.supply.url, timeout_s=s.supply.timeout_s)
        self.daq = DaqReader(s.daq.url, max_buffered_samples=4096)   # little stale data before each setpoint
        self.daq.start()
        self.cursor = DaqCursor(self.daq, s.daq.read_timeout_s)
        self.refresh_status()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.make_safe()
        for part in (self.daq, self.supply):
            with contextlib.suppress(Exception):
                if part is not None:
                    part.close()
        with contextlib.suppress(Exception):
            if self.bus is not None:
                self.bus.disconnect()
        self._status["connected"] = False

    # --- status ------------------------------------------------------------------------------------
    def refresh_status(self) -> dict[str, Any]:
        """Read drive/load/DAQ status; skipped (cached value returned) while a run holds the wires."""
        if not self._lock.acquire(timeout=0.05):
            return self.status()
        try:
            d = self.drive.read_status()
            l = self.load.read_status()
            c = self.daq.counters
            self._status.update({
                "connected": True, "error": None,
                "drive": {"state": d.state.value, "torque_nm": d.torque_nm, "speed_rpm": d.speed_rpm,
                          "udc_v": d.udc_v, "heartbeat_ok": self.drive.heartbeat_alive()},
                "load": {"state": l.state.value, "speed_rpm": l.speed_rpm},
                "daq": {"frames": c.frames, "crc_failures": c.crc_failures, "sequence_gaps": c.sequence_gaps},
            })
        except Exception as exc:  # status must never take the service down
            self._status.update({"error": f"{type(exc).__name__}: {exc}"})
        finally:
            self._lock.release()
        self._status["updated_at"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return self.status()

    def status(self) -> dict[str, Any]:
        return {**self._status, "busy": self.busy}

    # --- running an operating point ------------------------------------------------------------------
    def send_theta(self, theta_cos_rad: float, theta_sin_rad: float) -> None:
        """Theta to the drive; refuses (before anything is sent) a gamma above the run's gamma_max."""
        gamma_max = self._gamma_max_rad or math.radians(self.settings.identification.gamma_max_deg)
        if math.hypot(theta_cos_rad, theta_sin_rad) > gamma_max * (1 + 1e-9):
            raise LimitError(f"gamma {math.degrees(math.hypot(theta_cos_rad, theta_sin_rad)):.3f} deg exceeds gamma_max")
        self.drive.set_injection(theta_cos_rad, theta_sin_rad)

    def download_lut(self, image: bytes) -> int:
        """LUT image to the drive (segmented SDO), CRC-32 read back and compared; returns the CRC.
        Refused while a run holds the bench."""
        if not self._lock.acquire(timeout=1.0):
            raise BenchError("the bench is busy with a run; download the LUT when it is idle")
        try:
            return self.drive.download_lut(image)
        finally:
            self._lock.release()

    def setpoints_written(self) -> int:
        """Setpoints the drive has accepted so far; each toggles the DAQ sync line once (docs/interfaces.md)."""
        return self.drive.setpoints_written

    @contextlib.contextmanager
    def operating_point(self, op: OperatingPoint, harmonic_order: int, gamma_max_rad: float | None = None,
                        settle_s: float = 0.25) -> Iterator[OperatingPointSession]:
        """Go to `op`, settle on the DAQ clock, yield a measurement session; always leave safe.
        gamma_max_rad (default: settings) is enforced here and also set in the drive, which clamps."""
        check_limits(op, self.settings)
        s = self.settings
        with self._lock:
            self.busy = True
            self._gamma_max_rad = min(gamma_max_rad or math.inf, math.radians(self.settings.identification.gamma_max_deg))
            try:
                session = OperatingPointSession(self, self.cursor, harmonic_order, s.daq.sample_rate_hz,
                                                s.motor.pole_pairs, sync_input=s.daq.sync_input,
                                                no_sync_settle_s=s.daq.no_sync_settle_s, guard=self._guard,
                                                resonance=self.resonance)
                self._go_to(op, harmonic_order)
                session.settle_operating_point(op.speed_rpm, settle_s)
                session.reset_plant_time()
                yield session
            finally:
                try:
                    self.make_safe()
                finally:
                    self.busy = False
                    self._gamma_max_rad = None

    def _guard(self) -> None:
        """Checked before every DAQ read of a run: raises to stop it (operator cancel)."""
        if self.cancel_event is not None and self.cancel_event.is_set():
            raise RunCancelled("run cancelled")

    def _go_to(self, op: OperatingPoint, harmonic_order: int) -> None:
        self.supply.set_voltage(op.udc_v)
        self.supply.output(True)
        self._wait_supply(op.udc_v)
        self.load.enable()
        self.load.set_speed_rpm(op.speed_rpm)
        self.drive.enable()
        self.drive.set_gamma_max_rad(self._gamma_max_rad)
        self.drive.set_harmonic_order(harmonic_order)
        self.drive.set_decoupling(self.settings.identification.decoupling)
        self.drive.set_injection(0.0, 0.0)
        self.drive.set_injection_mode("manual")
        self.drive.set_torque_nm(op.torque_nm)

    def _wait_supply(self, udc_v: float, timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            measured = self.supply.measure_voltage()
            if abs(measured - udc_v) <= max(0.02 * udc_v, 0.05):
                return
            if time.monotonic() > deadline:
                raise BenchError(f"DC supply did not reach {udc_v:g} V within {timeout_s} s (measures {measured:g} V)")
            time.sleep(0.02)

    def make_safe(self, standstill_timeout_plant_s: float = 5.0) -> None:
        """Torque off, injection off, drive disabled, load stopped; then wait (on the DAQ clock,
        bounded) for standstill. Tries every step, raises the first error."""
        errors = []
        steps = []
        if self.drive is not None:
            steps.append(self.drive.disable)    # target torque 0, injection off, disable voltage
        if self.load is not None:
            steps.append(lambda: self.load.set_speed_rpm(0.0))
            if self.cursor is not None:
                # brake with the load's speed loop before disabling it (a disabled load coasts)
                steps.append(lambda: self._wait_standstill(standstill_timeout_plant_s))
            steps.append(self.load.disable)
        with self._lock:
            for step in steps:
                try:
                    step()
                except Exception as exc:
                    errors.append(exc)
                    log.error("make_safe step failed: %s", exc)
        if errors:
            raise BenchError(f"bench may not be safe: {errors[0]}") from errors[0]

    def _wait_standstill(self, timeout_plant_s: float, below_rpm: float = 20.0) -> None:
        """Consume the DAQ until the encoder shows the shaft below `below_rpm`."""
        block = int(0.02 * self.settings.daq.sample_rate_hz)
        for _ in range(int(timeout_plant_s / 0.02)):
            chunk = self.cursor.read(block).samples
            speed_rpm = mechanical_speed_rpm(chunk.angle_rad, self.settings.daq.sample_rate_hz, self.settings.motor.pole_pairs)
            if abs(speed_rpm) < below_rpm:
                return
        raise BenchError(f"shaft still turning {timeout_plant_s} s (plant time) after the stop command")
