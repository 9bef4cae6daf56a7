"""The bench as the service sees it: drive and load machine over CANopen, DAQ, DC supply.

Drivers are chosen by settings strings (CAN interface, pyserial URLs); nothing here knows whether
the bench is emulated. Safety (pymeasure's startup/execute/shutdown): every operating-point run
ends in `make_safe` (torque off, injection off, drive disabled, load stopped), also after an error
or a cancel, and every wait has a timeout.

Interlocks (service/bench/interlocks.py) are watched from their own thread during every run and between
runs: a trip takes the torque off at once (from a thread of its own: the CAN receive thread must
never wait for an SDO answer), stops the run at its next DAQ read (the session's guard), and the run
ends with InterlockTripped naming the first cause and make_safe's outcome. No run starts and no
torque is commanded while one is tripped. Before each run the setpoint/sync-toggle accounting is
re-established from the drive itself (commit counter read-back, DAQ quiet), so one SDO timeout or
a fault that dropped queued setpoints never poisons the runs after it.
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from datetime import datetime, timezone
from typing import Any, Callable, Iterator

from drivers.canopen_bus import CanBus
from drivers.cia402 import Command402
from drivers.daq_reader import DaqReader
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient, LutInForce
from drivers.lut_image import crc_hex
from drivers.errors import DaqError, DaqPortBusy, ForeignMasterError
from drivers.load_machine import LoadClient
from service.model.demodulation import ResonanceMode, ResonanceTracker
from service.model.harmonic import mechanical_speed_rpm
from service.bench.interlocks import (DaqLost, DeviceFault, ForeignMaster, HeartbeatLost, InterlockMonitor, InterlockTripped,
                                ServiceHeartbeatStopped, SupplyOutOfRange, Trip, daq_disconnected_reason)
from service.model import limits
from service.model.limits import LimitError
from service.bench.live_values import STALE_AFTER_S, LiveValues
from service.bench.run import BenchRun, gamma_max_for_run
from service.bench.measurement import OperatingPointSession, RunCancelled
from service.model.operating_point import OperatingPoint
from service.settings import Settings
from service.bench.setpoint_accounting import AccountingError, SetpointAccounting

log = logging.getLogger(__name__)


class BenchError(RuntimeError):
    pass


class BenchUnreachable(BenchError):
    """connect() failed: str() is one line naming the device, its address and what to check."""


class RunError(BenchError):
    """A run failed and make_safe failed too: the message names the first cause, then make_safe's error."""


class Bench:
    def __init__(self, settings: Settings, identity: str, on_trip: Callable[[Trip], None] | None = None):
        self.settings = settings
        self.identity = identity
        self.on_trip = on_trip                  # the service's reporter (SSE); called from the monitor thread
        self._lock = threading.RLock()          # one user of the wires at a time (SDO is not re-entrant)
        self.bus: CanBus | None = None
        self.drive: DriveClient | None = None
        self.load: LoadClient | None = None
        self.daq: DaqReader | None = None
        self.supply: ScpiSupply | None = None
        self.accounting: SetpointAccounting | None = None   # the drive's setpoints against the DAQ sync line
        self.interlocks: InterlockMonitor | None = None
        self._supply_interlock: SupplyOutOfRange | None = None
        self.busy = False
        self._gamma_max_rad: float | None = None  # of the run in progress
        self._run: BenchRun | None = None
        # the shaft mode of G_Salpha: the settings' pole, learned from the windows of every run (sec. 2.3)
        self.resonance = ResonanceTracker(ResonanceMode(settings.mechanics.pole_re_rad_s, settings.mechanics.pole_im_rad_s))
        self._auto_resets: list[float] = []     # monotonic times of automatic fault resets (rate limit)
        # link state, last error; "lut" is the drive's LUT objects (0x2001), read apart from its status
        self._devices: dict[str, dict[str, Any]] = {"drive": {}, "load": {}, "supply": {}, "lut": {}}
        self.live = LiveValues()                # every reading with its time (poller, the run's session, commands)
        self.unreachable: dict[str, str] | None = None   # {device, address, hint, error} when connect() failed
        self._status: dict[str, Any] = {"connected": False, "bench": identity, "busy": False,
                                        "drive": None, "load": None, "daq": None, "supply": None, "lut": None,
                                        "updated_at": None, "error": None}

    # --- lifecycle ---------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open every link; a link that fails raises BenchUnreachable naming the device, its address and
        what to check (nothing half-open is left behind)."""
        s = self.settings
        if not s.daq.url or not s.supply.url:
            raise BenchError("bench settings name no DAQ port (daq.url) or supply port (supply.url)")
        can_at = f"{s.can.interface} {s.can.channel}" + (f" at {s.can.host}:{s.can.port}" if s.can.host else "")
        steps = [
            ("CAN bus", can_at, "the CAN adapter or socketcand server is up and can.interface/channel/host/port name it",
             self._connect_bus),
            (f"drive (node {s.can.drive_node})", can_at, "the drive is powered, on the bus, and can.drive_node is its node id",
             self._connect_drive),
            (f"load machine (node {s.can.load_node})", can_at,
             "the load machine is powered, on the bus, and can.load_node is its node id", self._connect_load),
            ("DC supply", s.supply.url, "the supply is on and supply.url names its port", self._connect_supply),
            ("DAQ", s.daq.url, "the DAQ is plugged in and daq.url names its port", self._connect_daq),
        ]
        for device, address, hint, step in steps:
            try:
                step()
            except Exception as exc:
                self.close()
                if isinstance(exc, (ForeignMasterError, DaqPortBusy)):
                    # reached, but held by another master: the hint is to stop that one, not to check cables
                    hint = ("another service or tool is master of it (one service per bench): stop that one"
                            if isinstance(exc, ForeignMasterError) else "no other process holds the DAQ port (one "
                            "service per bench): stop the one that does")
                self.unreachable = {"device": device, "address": address, "hint": f"check that {hint}",
                                    "error": f"{type(exc).__name__}: {exc}"}
                raise BenchUnreachable(f"bench unreachable: {device} at {address} ({type(exc).__name__}: {exc}); "
                                       f"check that {hint}") from exc
        self.unreachable = None
        self.accounting = SetpointAccounting(self.daq, s.daq.read_timeout_s, lambda: self.drive.setpoints_written,
                                             self.drive.resync_setpoint_count)
        self.drive.on_setpoint = self.accounting.note_write
        self._start_interlocks()
        self._establish_accounting()
        self.refresh_status()

    def _establish_accounting(self) -> None:
        """Learn the DAQ sync line at connect, so the first run does not wait for it; a DAQ that does
        not stream yet leaves it to the first run."""
        if not self.settings.daq.sync_input:
            return
        with self._lock:
            try:
                self.accounting.establish(guard=lambda: None)
            except (DaqError, AccountingError) as exc:
                log.warning("setpoint accounting not established at connect (the first run does it): %s", exc)

    def _connect_bus(self) -> None:
        s = self.settings
        self.bus = CanBus(s.can.interface, s.can.channel, host=s.can.host, port=s.can.port, bitrate=s.can.bitrate,
                          service_node_id=s.can.service_node_id, heartbeat_period_ms=s.can.heartbeat_period_ms,
                          **s.can.options)
        # python-can logs every failed attempt as a warning; connect() says it once, with what to check
        can_log = logging.getLogger("can")
        level = can_log.level
        can_log.setLevel(logging.ERROR)
        try:
            self.bus.connect()
        finally:
            can_log.setLevel(level)

    def _connect_drive(self) -> None:
        self.drive = DriveClient(self.bus, self.settings.can.drive_node, sdo_timeout_s=self.settings.can.sdo_timeout_s)
        self.drive.connect()

    def _connect_load(self) -> None:
        self.load = LoadClient(self.bus, self.settings.can.load_node, sdo_timeout_s=self.settings.can.sdo_timeout_s)
        self.load.connect()

    def _connect_supply(self) -> None:
        self.supply = ScpiSupply(self.settings.supply.url, timeout_s=self.settings.supply.timeout_s)

    def _connect_daq(self) -> None:
        self.daq = DaqReader(self.settings.daq.url, max_buffered_samples=4096)   # little stale data before each setpoint
        self.daq.start()

    @property
    def connected(self) -> bool:
        return self.interlocks is not None and self.unreachable is None

    def _start_interlocks(self) -> None:
        il = self.settings.interlocks
        drive_fault, load_fault = DeviceFault(self.drive), DeviceFault(self.load)
        self._supply_interlock = SupplyOutOfRange(self.supply, il.supply_tolerance_fraction, il.supply_tolerance_v)
        self.interlocks = InterlockMonitor(
            [drive_fault, load_fault, HeartbeatLost(self.drive), HeartbeatLost(self.load),
             ServiceHeartbeatStopped(self.bus), ForeignMaster(self.bus), DaqLost(self.daq), self._supply_interlock],
            on_trip=self._tripped, period_s=il.monitor_period_s, stall_s=il.stall_s)
        self.drive.add_emcy_callback(lambda e: self.interlocks.emcy(drive_fault, e.code))
        self.load.add_emcy_callback(lambda e: self.interlocks.emcy(load_fault, e.code))
        self.interlocks.start()

    def close(self) -> None:
        """Orderly stop: drive and load disabled, then their heartbeat consumers disarmed (0x1016), then
        the links closed (the service heartbeat stops last): the devices do not fault, and the next
        start runs without a reset. connect() arms the consumers again."""
        if self.interlocks is not None:      # connected: leave it safe first
            with contextlib.suppress(Exception):
                self.make_safe()
            self.interlocks.stop()
            for device in (self.drive, self.load):
                try:
                    device.disarm_heartbeat_consumer()
                except Exception as exc:  # noqa: BLE001 - the device may be gone; it then faults as it should
                    log.warning("%s node %d: heartbeat consumer not disarmed (%s): it will fault when the "
                                "service's heartbeat stops", device.device_kind, device.node_id, exc)
        for part in (self.daq, self.supply):
            with contextlib.suppress(Exception):
                if part is not None:
                    part.close()
        with contextlib.suppress(Exception):
            if self.bus is not None:
                self.bus.disconnect()
        self._status["connected"] = False

    # --- interlocks ----------------------------------------------------------------------------------
    def _tripped(self, trip: Trip) -> None:
        """Monitor/CAN thread: torque off now if a run holds the bench, then report. The full make_safe
        (load braked to standstill) follows in the run's own thread when its guard raises."""
        if self.busy:
            threading.Thread(target=self._torque_off_now, name="ripplecal-trip-stop", daemon=True).start()
        if self.on_trip is not None:
            self.on_trip(trip)

    def _torque_off_now(self) -> None:
        try:
            self.drive.send_command(Command402.DISABLE_VOLTAGE)   # power stage off: no torque, no injection
        except Exception as exc:  # noqa: BLE001 - the drive may be the thing that is gone; make_safe retries
            log.warning("interlock: immediate torque off failed: %s", exc)

    def _guard(self, cancel: threading.Event | None = None) -> None:
        """Checked before every DAQ read of a run: raises to stop it (interlock trip, the run's cancel token)."""
        trip = self.interlocks.run_trip if self.interlocks is not None else None
        if trip is not None:
            raise InterlockTripped(trip)
        if cancel is not None and cancel.is_set():
            raise RunCancelled("run cancelled")

    def _require_clear(self) -> None:
        """Before anything that commands torque: refuse while an interlock is tripped (says which)."""
        trip = self.interlocks.run_trip or self.interlocks.refusal()
        if trip is not None:
            raise InterlockTripped(trip, refused=True)

    def _refuse_or_auto_reset(self) -> None:
        trip = self.interlocks.refusal()
        if trip is not None and trip.latched and self._auto_reset_allowed():
            log.warning("automatic fault reset (interlocks.auto_fault_reset) of: %s", trip.reason)
            self._auto_resets.append(time.monotonic())
            self._reset_devices()
            trip = self.interlocks.reset_latched()
        if trip is not None:
            raise InterlockTripped(trip, refused=True)

    def _auto_reset_allowed(self) -> bool:
        il = self.settings.interlocks
        if not il.auto_fault_reset:
            return False
        now = time.monotonic()
        self._auto_resets = [t for t in self._auto_resets if now - t < 3600.0]
        return len(self._auto_resets) < il.auto_fault_reset_per_hour

    @property
    def supply_interlock(self) -> SupplyOutOfRange:
        return self._supply_interlock

    def check_reachable(self) -> None:
        """Before a run is accepted: BenchUnreachable naming the device and what to check while the bench
        could not be reached at start (a run would only fail later)."""
        if self.unreachable is not None:
            raise BenchUnreachable(self._unreachable_trip().reason)

    def interlock_refusal(self) -> Trip | None:
        """What forbids a run now (None: clear to go); read fresh. A bench never reached forbids it too."""
        if self.unreachable is not None:
            return self._unreachable_trip()
        return self.interlocks.refusal() if self.interlocks is not None else None

    def _unreachable_trip(self) -> Trip:
        u = self.unreachable
        return Trip("bench_unreachable", f"{u['device']} at {u['address']} unreachable at start ({u['error']}); "
                    f"{u['hint']}, then restart the service", latched=False,
                    at=datetime.now(timezone.utc).isoformat(timespec="seconds"), monotonic=time.monotonic())

    def _reset_devices(self) -> dict[str, bool]:
        return {"drive": self.drive.fault_reset(), "load": self.load.fault_reset()}

    def fault_reset(self) -> dict[str, Any]:
        """A person acknowledges a fault: CiA 402 fault reset of the drive and the load (those in
        FAULT), then the latched interlocks are cleared if their condition has gone. Returns what was
        reset and what (if anything) still forbids a run."""
        if not self.connected:
            raise BenchError(self.interlock_refusal().reason)
        if not self._lock.acquire(timeout=2.0):
            raise BenchError("the bench is busy with a run; the run stops by itself on a trip, then reset")
        try:
            reset = self._reset_devices()
            remaining = self.interlocks.reset_latched()
        finally:
            self._lock.release()
        self.refresh_status()
        return {"reset": reset, "still_tripped": remaining.public() if remaining else None}

    # --- status ------------------------------------------------------------------------------------
    def refresh_status(self) -> dict[str, Any]:
        """Read drive/load/supply by SDO/SCPI, each on its own (one failing device does not hide the
        others), never under the run lock: each device's link has a lock of its own (the interlock
        monitor reads the same way), so the view stays live while a run holds the bench, and a fault
        reset or a LUT download on an idle bench never waits for the poller (they take the run lock).
        The LUT the drive holds changes only by a download (which publishes it), so its objects are read
        when no run holds the bench, and not while the drive does not answer (its status read says so,
        without three more timeouts)."""
        if self.connected:
            self._read_devices()
            if not self.busy and self._devices["drive"].get("last_error") is None:
                self._read_device("lut", self.drive.lut_in_force, _lut_shape)
        self._status["updated_at"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return self.status()

    def _read_devices(self) -> None:
        self._read_device("drive", lambda: self.drive.read_status(), lambda d: {
            "state": d.state.value, "torque_nm": d.torque_nm, "speed_rpm": d.speed_rpm, "udc_v": d.udc_v})
        self._read_device("load", lambda: self.load.read_status(), lambda l: {
            "state": l.state.value, "speed_rpm": l.speed_rpm})
        self._read_device("supply", lambda: self.supply.measure_voltage(), lambda v: {"measured_v": v})

    def _read_device(self, name: str, read, shape) -> None:
        entry = self._devices[name]
        try:
            self.live.publish(name, **shape(read()))
            entry["last_error"] = None
        except Exception as exc:  # status must never take the service down
            entry["last_error"] = f"{type(exc).__name__}: {exc}"

    def status(self) -> dict[str, Any]:
        """The truth per device: live link state (heartbeats, DAQ port) plus the last readings, each
        with its age (`ages`, s) and `stale` past STALE_AFTER_S; `run`: what the run in flight sees on
        the DAQ (encoder speed, the h-th acceleration amplitude); `error` is the first thing wrong."""
        s = self.settings
        common = {"busy": self.busy, "stale_after_s": STALE_AFTER_S,
                  "accel_full_scale_rad_s2": s.daq.accel_full_scale_rad_s2}
        if not self.connected:
            u = self.unreachable
            return {**self._status, **common, "connected": False, "unreachable": u,
                    "error": self._unreachable_trip().reason if u else self._status.get("error")}
        out = {**self._status, **common, "connected": bool(self.bus and self.bus.connected), "unreachable": None}

        def device(name: str, live: dict[str, Any]) -> dict[str, Any]:
            values, ages = self.live.group(name)
            oldest = max(ages.values()) if ages else None
            return {**values, **self._devices[name], **live, "ages": ages, "age_s": oldest,
                    "stale": oldest is None or oldest > STALE_AFTER_S}

        for name, dev in (("drive", self.drive), ("load", self.load)):
            age = dev.heartbeat_age_s()
            out[name] = device(name, {"connected": dev.heartbeat_alive(), "heartbeat_ok": dev.heartbeat_alive(),
                                      "heartbeat_age_s": None if age is None else round(age, 2)})
        out["supply"] = device("supply", {"url": s.supply.url})
        out["supply"]["connected"] = out["supply"].get("last_error") is None and out["supply"]["age_s"] is not None
        out["lut"] = device("lut", {})     # read when idle and at each download: its age says when
        c = self.daq.counters
        out["daq"] = {**self.daq.health(), "frames": c.frames, "crc_failures": c.crc_failures,
                      "sequence_gaps": c.sequence_gaps}
        run, run_ages = self.live.group("run")
        if run.get("harmonic_amplitude_fs") is not None:
            run["harmonic_amplitude_rad_s2"] = run["harmonic_amplitude_fs"] * s.daq.accel_full_scale_rad_s2
            run_ages["harmonic_amplitude_rad_s2"] = run_ages["harmonic_amplitude_fs"]
        out["run"] = {**run, "active": self.busy, "ages": run_ages}
        out["service_heartbeat_ok"] = self.bus.heartbeat_producing()
        out["interlocks"] = self.interlocks.snapshot()
        problems = [t["reason"] for t in out["interlocks"]["tripped"]]
        if not out["daq"]["connected"] and not any(p.startswith("DAQ") for p in problems):
            # the link is known lost before the interlock's next round names it
            problems.append(daq_disconnected_reason(out["daq"]["url"], out["daq"]["last_error"]))
        problems += [f"{n}: {out[n]['last_error']}" for n in ("drive", "load", "supply") if out[n].get("last_error")]
        out["error"] = problems[0] if problems else None
        return out

    # --- running an operating point ------------------------------------------------------------------
    def send_theta(self, theta_cos_rad: float, theta_sin_rad: float, cancel: threading.Event | None = None) -> None:
        """Theta to the drive; refuses (before anything is sent) a gamma above the run's gamma_max."""
        gamma_max = self._gamma_max_rad or math.radians(self.settings.identification.gamma_max_deg)
        if math.hypot(theta_cos_rad, theta_sin_rad) > gamma_max * (1 + 1e-9):
            raise LimitError(f"gamma {math.degrees(math.hypot(theta_cos_rad, theta_sin_rad)):.3f} deg exceeds gamma_max")
        self._guard(cancel)
        self.drive.set_injection(theta_cos_rad, theta_sin_rad)

    def send_injection_mode(self, mode: str, cancel: threading.Event | None = None) -> None:
        """Injection mode to the drive (off / manual / lut) during a run; make_safe sets it off again."""
        self._guard(cancel)
        self.drive.set_injection_mode(mode)

    def set_dc_link(self, udc_v: float) -> None:
        """The supply to udc_v and confirmed; the supply interlock watches the new band from then on."""
        self._supply_interlock.expected_v = None     # not out of range while it changes
        self.supply.set_voltage(udc_v)
        self.supply.output(True)
        self._wait_supply(udc_v)
        self._supply_interlock.expected_v = udc_v

    def download_lut(self, image: bytes) -> LutInForce:
        """LUT image to the drive (segmented SDO), CRC-32 read back and compared; returns what the
        drive now holds (map id, CRC, status), which /bench/status shows from then on. Refused while
        a run holds the bench."""
        if not self.connected:
            raise BenchError(self.interlock_refusal().reason)
        if not self._lock.acquire(timeout=1.0):
            raise BenchError("the bench is busy with a run; download the LUT when it is idle")
        try:
            held = self.drive.download_lut(image)
            self._read_device("lut", lambda: held, _lut_shape)      # the drive's own read-back
            return held
        finally:
            self._lock.release()

    def setpoints_written(self) -> int:
        """Setpoints the drive has accepted so far; each toggles the DAQ sync line once (docs/interfaces.md)."""
        return self.drive.setpoints_written

    @contextlib.contextmanager
    def run(self, harmonic_order: int, gamma_max_rad: float | None = None, decoupling: bool | None = None,
            cancel: threading.Event | None = None) -> Iterator[BenchRun]:
        """One continuous run (service/bench/run.py): the bench held, the interlocks armed throughout,
        moves from point to point; make_safe when it ends, however it ends. gamma_max_rad (default:
        settings) is enforced here and also set in the drive, which clamps; decoupling (default:
        settings) is the drive's 0x2000:6 for the run. Refused (InterlockTripped, nothing commanded)
        while an interlock is tripped. `cancel` set stops the run at its next DAQ read."""
        if not self.connected:
            raise InterlockTripped(self._unreachable_trip(), refused=True)
        with self._lock:
            self._refuse_or_auto_reset()
            self.busy = True
            self._gamma_max_rad = gamma_max_for_run(gamma_max_rad, limits.gamma_max_rad(None, self.settings))
            run = BenchRun(self, harmonic_order, self._gamma_max_rad,
                           self.settings.identification.decoupling if decoupling is None else decoupling, cancel)
            self._run = run
            self.interlocks.arm()
            first: BaseException | None = None
            try:
                self.accounting.start_run(run.guard)
                yield run
            except BaseException as exc:
                first = exc
            self._end_run(first)

    @contextlib.contextmanager
    def operating_point(self, op: OperatingPoint, harmonic_order: int, gamma_max_rad: float | None = None,
                        cancel: threading.Event | None = None, on_window: Callable | None = None,
                        decoupling: bool | None = None, target_db: float = 40.0) -> Iterator[OperatingPointSession]:
        """A run of one point: go to `op`, settle, yield the session; the bench is left safe after it."""
        with self.run(harmonic_order, gamma_max_rad, decoupling, cancel) as run:
            with run.operating_point(op, target_db=target_db, on_window=on_window) as session:
                yield session

    def _end_run(self, first: BaseException | None) -> None:
        """After a run (clean or not): learn whether an interlock is the first cause, make safe, and
        raise what happened: the trip (with make_safe's outcome), else the run's own error (with
        make_safe's error added if it failed too), else make_safe's error."""
        try:
            if first is not None and not isinstance(first, (RunCancelled, GeneratorExit)):
                self.interlocks.check_now(force=True)     # an EMCY/FAULT may be why the run failed
            trip = self.interlocks.disarm()
            if trip is not None:
                self.accounting.doubt("an interlock tripped during the run")   # a faulted drive drops what it queued
            if self._supply_interlock is not None:
                self._supply_interlock.expected_v = None
            safe_error: Exception | None = None
            try:
                self.make_safe()
            except Exception as exc:
                safe_error = exc
            self.accounting.end_run()
        finally:
            self.busy = False
            self._gamma_max_rad = None
            self._run = None
            if self.connected:
                self._read_devices()    # the status shows the state the run left, not the poller's last read
        outcome = "bench made safe" if safe_error is None else f"make_safe failed: {safe_error}"
        if trip is not None and not isinstance(first, GeneratorExit):
            err = InterlockTripped(trip, outcome=outcome)
            if first is not None and not isinstance(first, InterlockTripped):
                err.add_note(f"the run then failed with {type(first).__name__}: {first}")
            raise err from first
        if first is not None:
            if safe_error is None:
                raise first
            raise RunError(f"{type(first).__name__}: {first}; then {outcome}") from first
        if safe_error is not None:
            raise BenchError(f"bench may not be safe: {safe_error}") from safe_error

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
        """Torque off, injection off, drive disabled, load stopped; then wait (on the DAQ clock, or on
        the load's own speed reading if the DAQ is gone; bounded) for standstill. Tries every step,
        raises the first error."""
        errors = []
        steps = []
        if self.drive is not None:
            steps.append(self.drive.disable)    # target torque 0, injection off, disable voltage
        if self.load is not None:
            steps.append(lambda: self.load.set_speed_rpm(0.0))
            if self.accounting is not None:
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
        """Consume the DAQ until the encoder shows the shaft below `below_rpm` (bounded on the DAQ
        clock); without a DAQ, poll the load machine's velocity actual instead (wall clock, same bound)."""
        rate = self.settings.daq.sample_rate_hz
        block = int(0.02 * rate)
        cursor = self.accounting.cursor
        try:
            start = None
            while start is None or cursor.last_index - start < timeout_plant_s * rate:
                chunk = cursor.read(block).samples
                start = int(chunk.index[0]) if start is None else start
                try:    # over the block's contiguous runs: the angle's step across a DAQ gap is unknown
                    speed_rpm = mechanical_speed_rpm(chunk.angle_rad, rate, self.settings.motor.pole_pairs,
                                                     chunk.gap_before)
                except ValueError:
                    continue
                if abs(speed_rpm) < below_rpm:
                    return
        except DaqError as exc:
            log.warning("standstill judged on the load's speed: DAQ unavailable (%s)", exc)
            self.accounting.doubt("the DAQ was unavailable at the end of a run")
            deadline = time.monotonic() + timeout_plant_s
            while time.monotonic() < deadline:
                speed_rpm = self.load.read_status().speed_rpm
                if abs(speed_rpm) < below_rpm:
                    return
                time.sleep(0.02)
        raise BenchError(f"shaft still turning {timeout_plant_s:g} s (plant time, DAQ sample clock) after the stop command")


def _lut_shape(held: LutInForce) -> dict[str, Any]:
    """The LUT the drive holds as /bench/status shows it: no map id and no CRC while it holds none."""
    return {"map_id": held.map_id or None, "crc32": crc_hex(held.crc32) if held.map_id else None,
            "status": held.status}
