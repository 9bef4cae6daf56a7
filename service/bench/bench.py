"""The bench as the service sees it: drive and load machine over CANopen, DAQ, DC supply.

`Bench` is the facade the service, the engine, the routes and the CLI use; the work is done by its
parts, each given what it needs (calls go downward only; `busy` and `after_run` are callbacks):
  - `BenchLinks` (service/bench/connections.py): the links, connect/close, reachability;
  - `BenchFaults` (service/bench/faults.py): the interlocks, trips, refusals, fault resets;
  - `RunLifecycle` (service/bench/lifecycle.py): runs (open, the commands during one, end),
    make_safe, the setpoint accounting, and the bench watchdog (service/bench/watchdog.py) that makes
    the bench safe from its own thread when a run's loop goes silent or a stop is asked (`stop_now`);
  - `BenchStatus` (service/bench/status.py): the /bench/status view and the poller's reads.
A run (service/bench/run.py) is given the facade as its `RunBench` (service/bench/contracts.py).
"""

from __future__ import annotations

import contextlib
import threading
from contextlib import AbstractContextManager
from typing import Any, Callable

from drivers.canopen_bus import CanBus
from drivers.daq_reader import DaqReader
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient, LutInForce
from drivers.load_machine import LoadClient
from service.bench.connections import BenchLinks
from service.bench.errors import BenchError, BenchUnreachable, RunError
from service.bench.faults import BenchFaults
from service.bench.interlock_monitor import InterlockMonitor
from service.bench.interlocks import ActualsOutsideLimits, SupplyOutOfRange
from service.bench.lifecycle import RunLifecycle
from service.bench.live_values import LiveValues
from service.bench.measurement import OperatingPointSession
from service.bench.run import BenchRun
from service.bench.setpoint_accounting import SetpointAccounting
from service.bench.status import BenchStatus
from service.bench.trips import Trip
from service.identification.session import Window
from service.model.demodulation import ResonanceMode, ResonanceTracker
from service.model.operating_point import OperatingPoint
from service.settings import Settings

__all__ = ["Bench", "BenchError", "BenchUnreachable", "RunError"]

CLOSE_SAFE_WAIT_S = 5.0  # a shutdown waits this long for the watchdog's stop (each SDO step is bounded)
CLOSE_LOCK_WAIT_S = 2.0  # ... and this long for the run lock before its own make_safe (a stuck worker holds it)


class Bench:
    """The bench (module doc); also the `RunBench` its runs are given."""

    def __init__(self, settings: Settings, identity: str, on_trip: Callable[[Trip], None] | None = None):
        self.settings = settings
        self.identity = identity
        lock = threading.RLock()  # one user of the wires at a time (SDO is not re-entrant)
        self._lock = lock
        # an SDO answered on the run's own thread tells the watchdog the run is at work (a slow bus)
        self._links = BenchLinks(settings, on_answer=lambda: self._runs.watchdog.bus_answered())
        # on_trip: the service's reporter (SSE); called from the monitor thread
        self._faults = BenchFaults(settings, self._links, lock, busy=lambda: self._runs.busy, on_trip=on_trip)
        self._runs = RunLifecycle(settings, self._links, self._faults, lock, after_run=self._after_run)
        self._view = BenchStatus(settings, identity, self._links, self._faults, busy=lambda: self._runs.busy)
        # the shaft mode of G_Salpha: the settings' pole, learned from the windows of every run (sec. 2.3)
        self.resonance = ResonanceTracker(
            ResonanceMode(settings.mechanics.pole_re_rad_s, settings.mechanics.pole_im_rad_s)
        )

    # --- the parts' state, as the layers above read it --------------------------------------------------
    @property
    def bus(self) -> CanBus | None:
        return self._links.bus

    @property
    def drive(self) -> DriveClient | None:
        return self._links.drive

    @property
    def load(self) -> LoadClient | None:
        return self._links.load

    @property
    def daq(self) -> DaqReader | None:
        return self._links.daq

    @property
    def supply(self) -> ScpiSupply | None:
        return self._links.supply

    @property
    def unreachable(self) -> dict[str, str] | None:
        """{device, address, hint, error} when connect() failed."""
        return self._links.unreachable

    @property
    def connected(self) -> bool:
        return self._faults.connected

    @property
    def on_trip(self) -> Callable[[Trip], None] | None:
        return self._faults.on_trip

    @on_trip.setter
    def on_trip(self, on_trip: Callable[[Trip], None] | None) -> None:
        self._faults.on_trip = on_trip

    # the parts a run reads (its RunBench): BenchError while the bench is not connected
    @property
    def interlocks(self) -> InterlockMonitor:
        return self._faults.started().monitor

    @property
    def supply_interlock(self) -> SupplyOutOfRange:
        return self._faults.started().supply

    @property
    def actuals(self) -> ActualsOutsideLimits:
        """The drive's actuals held against the limits; also a point's mean torque actual."""
        return self._faults.started().actuals

    @property
    def accounting(self) -> SetpointAccounting:
        """The drive's setpoints against the DAQ sync line."""
        return self._runs.accounting

    @property
    def busy(self) -> bool:
        return self._runs.busy

    @property
    def live(self) -> LiveValues:
        return self._view.live

    # --- connections -------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open every link (BenchUnreachable naming the device, its address and what to check, nothing
        half-open left behind), count setpoints against the DAQ sync line, start the interlocks."""
        self._links.open()
        self._runs.attach_accounting()
        self._faults.start()
        self._runs.establish_accounting()
        self._runs.watchdog.start()
        self.refresh_status()

    def close(self) -> None:
        """Orderly stop: drive and load disabled, then their heartbeat consumers disarmed (0x1016), then
        the links closed (the service heartbeat stops last): the devices do not fault, and the next
        start runs without a reset. connect() arms the consumers again."""
        if self._faults.interlocks is not None:  # connected: leave it safe first
            # at once, whatever the worker is doing (it may hold the run lock, stuck on the database)
            self.stop_now("the service is shutting down")
            self._runs.watchdog.wait_safe(CLOSE_SAFE_WAIT_S)
            with contextlib.suppress(Exception):
                self._runs.make_safe(lock_timeout_s=CLOSE_LOCK_WAIT_S)
            self._runs.watchdog.close()
            self._faults.stop()
            self._links.disarm_heartbeat_consumers()
        self._links.close()
        self._view.mark_closed()

    def check_reachable(self) -> None:
        """Before a run is accepted: BenchUnreachable while the bench could not be reached at start."""
        self._links.check_reachable()

    # --- faults ------------------------------------------------------------------------------------------
    def interlock_refusal(self) -> Trip | None:
        """What forbids a run now (None: clear to go); read fresh. A bench never reached forbids it too."""
        return self._faults.refusal()

    def fault_reset(self) -> dict[str, Any]:
        """A person acknowledges a fault (BenchFaults.fault_reset); the status is read again after it."""
        result = self._faults.fault_reset()
        self.refresh_status()
        return result

    def stop_now(self, reason: str) -> None:
        """A cancel or a shutdown: drive and load disabled at once by the watchdog's thread if a run holds
        the bench, whatever its worker is doing. Never blocks (no lock, no I/O: safe in a signal handler)."""
        self._runs.watchdog.request_stop(reason)

    # --- status ------------------------------------------------------------------------------------------
    def refresh_status(self) -> dict[str, Any]:
        """Read drive/load/supply (and the LUT when idle) and return the status (BenchStatus.refresh)."""
        return self._view.refresh()

    def status(self) -> dict[str, Any]:
        """The truth per device, with ages and the first thing wrong (BenchStatus.status), and the bench
        watchdog's latest stop (why the bench was made safe under a run)."""
        status = self._view.status()
        watchdog = self._runs.watchdog
        stopped = watchdog.last_stop
        status["watchdog"] = {
            "bound_s": watchdog.bound_s,
            "last_stop": stopped.public() if stopped else None,
            "silent_since_monotonic": watchdog.silent_since_monotonic,  # the host's CLOCK_MONOTONIC (fault timing)
        }
        if watchdog.tripped is not None and self._runs.busy and not status.get("error"):
            status["error"] = watchdog.tripped.reason  # the run in progress was stopped under it
        return status

    def _after_run(self) -> None:
        if self.connected:
            self._view.read_devices()  # the status shows the state the run left, not the poller's last read

    # --- runs --------------------------------------------------------------------------------------------
    def run(
        self,
        harmonic_order: int,
        gamma_max_rad: float | None = None,
        decoupling: bool | None = None,
        cancel: threading.Event | None = None,
    ) -> AbstractContextManager[BenchRun]:
        """One continuous run (RunLifecycle.run): the bench held and watched, made safe when it ends."""
        return self._runs.run(self, harmonic_order, gamma_max_rad, decoupling, cancel)

    def operating_point(
        self,
        op: OperatingPoint,
        harmonic_order: int,
        gamma_max_rad: float | None = None,
        cancel: threading.Event | None = None,
        on_window: Callable[[Window], None] | None = None,
        decoupling: bool | None = None,
        target_db: float = 40.0,
    ) -> AbstractContextManager[OperatingPointSession]:
        """A run of one point: go to `op`, settle, yield the session; the bench is left safe after it."""
        return self._runs.operating_point(
            self, op, harmonic_order, gamma_max_rad, cancel, on_window, decoupling, target_db
        )

    def make_safe(self, standstill_timeout_plant_s: float = 5.0) -> None:
        """Torque off, injection off, drive disabled, load stopped (RunLifecycle.make_safe)."""
        self._runs.make_safe(standstill_timeout_plant_s)

    def setpoints_written(self) -> int:
        """Setpoints the drive has accepted so far; each toggles the DAQ sync line once (docs/interfaces.md)."""
        return self._links.opened().drive.setpoints_written

    def download_lut(self, image: bytes) -> LutInForce:
        """LUT image to the drive (segmented SDO), CRC-32 read back and compared; returns what the
        drive now holds (map id, CRC, status), which /bench/status shows from then on. Refused while
        a run holds the bench."""
        if not self.connected:
            raise BenchError(self._links.unreachable_trip().reason)  # what interlock_refusal() says of it
        if not self._lock.acquire(timeout=1.0):
            raise BenchError("the bench is busy with a run; download the LUT when it is idle")
        try:
            held = self._links.opened().drive.download_lut(image)
            self._view.read_lut(lambda: held)  # the drive's own read-back
            return held
        finally:
            self._lock.release()
