"""The bench's fault handling: the interlocks, what a trip does, refusals and fault resets.

Interlocks (service/bench/interlocks.py) are watched from their own thread during every run and
between runs: a trip takes the torque off at once (from a thread of its own: the CAN receive thread
must never wait for an SDO answer), stops the run at its next DAQ read (`guard`), and the run ends
with InterlockTripped naming the first cause and make_safe's outcome (service/bench/lifecycle.py).
No run starts and no torque is commanded while one is tripped. A latched trip is cleared by a
person's `fault_reset`, or, where the settings allow it, automatically before a run (rate-limited).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from drivers.cia402 import Command402
from drivers.drive import DriveActuals
from service.bench.connections import BenchLinks
from service.bench.errors import BenchError
from service.bench.interlock_monitor import InterlockMonitor
from service.bench.interlocks import (
    ActualsOutsideLimits,
    DaqLost,
    DeviceFault,
    ForeignMaster,
    HeartbeatLost,
    ServiceHeartbeatStopped,
    SupplyOutOfRange,
)
from service.bench.measurement import RunCancelled
from service.bench.trips import InterlockTripped, Trip
from service.settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchInterlocks:
    """The interlocks of a connected bench (BenchFaults.start): the monitor over all of them, and the two a
    run talks to: the supply's band it sets, the actuals whose mean torque it reads."""

    monitor: InterlockMonitor
    supply: SupplyOutOfRange
    actuals: ActualsOutsideLimits


class BenchFaults:
    """Interlocks over the bench's links (module doc). `busy()` says whether a run holds the bench (a
    trip then takes the torque off at once); `on_trip(trip)` is the service's reporter, called from
    the monitor thread; `lock` is the bench's run lock (one user of the wires at a time)."""

    def __init__(
        self,
        settings: Settings,
        links: BenchLinks,
        lock: threading.RLock,
        busy: Callable[[], bool],
        on_trip: Callable[[Trip], None] | None = None,
    ):
        self.settings = settings
        self.links = links
        self._lock = lock
        self._busy = busy
        self.on_trip = on_trip
        self._started: BenchInterlocks | None = None  # set by start()
        self._auto_resets: list[float] = []  # monotonic times of automatic fault resets (rate limit)

    @property
    def interlocks(self) -> InterlockMonitor | None:
        """The interlock monitor (None until start())."""
        return self._started.monitor if self._started is not None else None

    @property
    def supply_interlock(self) -> SupplyOutOfRange | None:
        return self._started.supply if self._started is not None else None

    @property
    def actuals(self) -> ActualsOutsideLimits | None:
        """The envelope held on what the motor does (None until start())."""
        return self._started.actuals if self._started is not None else None

    def started(self) -> BenchInterlocks:
        """The interlocks, for what needs the bench watched (a run, a fault reset, the status); BenchError
        before start()."""
        if self._started is None:
            raise BenchError("the bench is not connected: its interlocks are not watching")
        return self._started

    @property
    def connected(self) -> bool:
        """The bench was reached and is watched (interlocks started)."""
        return self._started is not None and self.links.unreachable is None

    def start(self) -> None:
        """Build the interlocks over the open links and start watching."""
        il = self.settings.interlocks
        links = self.links.opened()
        drive, load = links.drive, links.load
        drive_fault, load_fault = DeviceFault(drive), DeviceFault(load)
        supply = SupplyOutOfRange(links.supply, il.supply_tolerance_fraction, il.supply_tolerance_v)
        actuals = ActualsOutsideLimits(drive, self.settings.safety, self.settings.motor.i_max_a)
        monitor = InterlockMonitor(
            [
                drive_fault,
                load_fault,
                HeartbeatLost(drive),
                HeartbeatLost(load),
                ServiceHeartbeatStopped(links.bus),
                ForeignMaster(links.bus),
                DaqLost(links.daq),
                supply,
                actuals,
            ],
            on_trip=self._tripped,
            period_s=il.monitor_period_s,
            stall_s=il.stall_s,
        )
        self._started = BenchInterlocks(monitor, supply, actuals)
        drive.add_emcy_callback(lambda e: monitor.emcy(drive_fault, e.code))
        load.add_emcy_callback(lambda e: monitor.emcy(load_fault, e.code))
        drive.on_actuals = self._on_actuals
        monitor.start()

    def _on_actuals(self, actuals: DriveActuals) -> None:
        """Every TPDO of the drive's actuals (CAN receive thread): into the point's mean, then decided at once."""
        try:
            started = self.started()
            started.actuals.push(actuals)
            started.monitor.pushed(started.actuals, actuals)
        except Exception:  # noqa: BLE001 - the receive thread must go on; the monitor's poll still reads them
            log.exception("actuals interlock: a TPDO could not be decided")

    def _tripped(self, trip: Trip) -> None:
        """Monitor/CAN thread: torque off now if a run holds the bench, then report. The full make_safe
        (load braked to standstill) follows in the run's own thread when its guard raises."""
        if self._busy():
            threading.Thread(target=self._torque_off_now, name="ripplecal-trip-stop", daemon=True).start()
        if self.on_trip is not None:
            self.on_trip(trip)

    def _torque_off_now(self) -> None:
        try:
            # power stage off: no torque, no injection
            self.links.opened().drive.send_command(Command402.DISABLE_VOLTAGE)
        except Exception as exc:  # noqa: BLE001 - the drive may be the thing that is gone; make_safe retries
            log.warning("interlock: immediate torque off failed: %s", exc)

    # --- during a run --------------------------------------------------------------------------------
    def guard(self, cancel: threading.Event | None = None) -> None:
        """Checked before every DAQ read of a run: raises to stop it (interlock trip, the run's cancel token)."""
        trip = self.interlocks.run_trip if self.interlocks is not None else None
        if trip is not None:
            raise InterlockTripped(trip)
        if cancel is not None and cancel.is_set():
            raise RunCancelled("run cancelled")

    # --- refusals and resets -------------------------------------------------------------------------
    def refusal(self) -> Trip | None:
        """What forbids a run now (None: clear to go); read fresh. A bench never reached forbids it too."""
        if self.links.unreachable is not None:
            return self.links.unreachable_trip()
        return self.interlocks.refusal() if self.interlocks is not None else None

    def refuse_or_auto_reset(self) -> None:
        """Before a run: refuse while an interlock is tripped, unless a latched trip may be reset
        automatically (interlocks.auto_fault_reset, rate-limited)."""
        monitor = self.started().monitor
        trip = monitor.refusal()
        if trip is not None and trip.latched and self._auto_reset_allowed():
            log.warning("automatic fault reset (interlocks.auto_fault_reset) of: %s", trip.reason)
            self._auto_resets.append(time.monotonic())
            self._reset_devices()
            trip = monitor.reset_latched()
        if trip is not None:
            raise InterlockTripped(trip, refused=True)

    def _auto_reset_allowed(self) -> bool:
        il = self.settings.interlocks
        if not il.auto_fault_reset:
            return False
        now = time.monotonic()
        self._auto_resets = [t for t in self._auto_resets if now - t < 3600.0]
        return len(self._auto_resets) < il.auto_fault_reset_per_hour

    def _reset_devices(self) -> dict[str, bool]:
        links = self.links.opened()
        return {"drive": links.drive.fault_reset(), "load": links.load.fault_reset()}

    def fault_reset(self) -> dict[str, Any]:
        """A person acknowledges a fault: CiA 402 fault reset of the drive and the load (those in
        FAULT), then the latched interlocks are cleared if their condition has gone. Returns what was
        reset and what (if anything) still forbids a run."""
        if not self.connected:
            raise BenchError(self.links.unreachable_trip().reason)  # what refusal() says of a bench not watched
        if not self._lock.acquire(timeout=2.0):
            raise BenchError("the bench is busy with a run; the run stops by itself on a trip, then reset")
        try:
            reset = self._reset_devices()
            remaining = self.started().monitor.reset_latched()
        finally:
            self._lock.release()
        return {"reset": reset, "still_tripped": remaining.public() if remaining else None}

    def stop(self) -> None:
        self.started().monitor.stop()
