"""The interlock monitor: watches the interlocks (service/bench/interlocks.py) from a thread of its own.

EMCY and the drive's actuals arrive pushed, from the CAN receive thread, and are decided there at once;
the rest are polled, each at its own period. The monitor keeps the first trip of the run in flight
(`run_trip`, read by the bench's guard before every DAQ read) and calls `on_trip` at once, so the bench
goes safe without waiting for the run to notice. Between runs it answers whether a run may start
(`refusal`) and clears latched trips after a person's fault reset (`reset_latched`).
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import datetime, timezone
from typing import Any, Callable

from service.bench.interlocks import DeviceFault, Interlock
from service.bench.trips import Trip

log = logging.getLogger(__name__)


class InterlockMonitor:
    """Watches the interlocks from a thread of its own; keeps the first trip of the run in flight.

    on_trip(trip) is called (from the monitor or CAN thread) for every new trip while a run is armed,
    and for latched trips at any time; it must be quick and must not take the bench's run lock.
    stall_s: a gap this long between two monitor rounds means the process stalled: the drive has then
    missed our heartbeat for about that long, which trips the run in flight.
    """

    def __init__(
        self, interlocks: list[Interlock], on_trip: Callable[[Trip], None], period_s: float = 0.05, stall_s: float = 0.5
    ):
        self.interlocks = interlocks
        self.on_trip = on_trip
        self.period_s = period_s
        self.stall_s = stall_s
        self._lock = threading.Lock()
        self._armed = False
        self._run_trip: Trip | None = None
        self._last_trip: Trip | None = None
        self._reported: dict[str, str] = {}  # interlock -> reason already reported (no repeats while it holds)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle --------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="ripplecal-interlocks", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _loop(self) -> None:
        while True:
            slept_from = time.monotonic()
            if self._stop.wait(self.period_s):
                return
            # only the sleep is timed: a round's own slow reads (an SDO timeout) are not a stall
            overslept = time.monotonic() - slept_from - self.period_s
            with self._lock:
                armed = self._armed
            if armed and overslept > self.stall_s:
                self._tripped(
                    "service_stall",
                    f"heartbeat lost: the service stalled for {overslept:.1f} s (its heartbeat to the drive lapsed)",
                    latched=False,
                )
            try:
                self.check_now()
            except Exception:  # noqa: BLE001 - the watchdog must outlive any one bad reading
                log.exception("interlock monitor round failed")

    # --- runs ---------------------------------------------------------------------------------------
    def arm(self) -> None:
        with self._lock:
            self._armed = True
            self._run_trip = None
            for lock in self.interlocks:
                lock.armed_changed(True)
            # an armed-only interlock is not read between runs: a reason from the last run is stale
            for lock in self.interlocks:
                if lock.armed_only and not lock.latched:
                    lock.reason = None
                    self._reported.pop(lock.name, None)

    def check(self, interlock: "Interlock") -> Trip | None:
        """Read one interlock now (e.g. the supply before a point is committed: its monitor period may
        be longer than a point); returns the run's first trip."""
        reason = interlock.evaluate()
        if reason is not None:
            self._tripped(interlock.name, reason, interlock.latched)
        return self.run_trip

    def disarm(self) -> Trip | None:
        """End of a run: returns its first trip (None if it ran clean)."""
        with self._lock:
            self._armed = False
            for lock in self.interlocks:
                lock.armed_changed(False)
            trip, self._run_trip = self._run_trip, None
            return trip

    @property
    def run_trip(self) -> Trip | None:
        with self._lock:
            return self._run_trip

    # --- evaluation -----------------------------------------------------------------------------------
    def check_now(self, force: bool = False) -> Trip | None:
        """One round over every interlock that is due (all of them with force; callable from any
        thread, e.g. on a run's error path to learn whether an interlock is the first cause). Returns
        the run's first trip."""
        now = time.monotonic()
        with self._lock:
            armed = self._armed
        for lock in self.interlocks:
            if lock.armed_only and not armed:
                continue
            if not lock.due(now) and not force:
                if lock.reason is not None:
                    self._tripped(lock.name, lock.reason, lock.latched)
                continue
            reason = lock.evaluate()
            if reason is not None:
                self._tripped(lock.name, reason, lock.latched)
            else:
                with self._lock:
                    self._reported.pop(lock.name, None)
        return self.run_trip

    def pushed(self, interlock: Interlock, value: Any) -> None:
        """A value pushed to `interlock` (the drive's actuals, CAN receive thread): decided now, not at the
        next monitor round, so a trip takes the torque off within the push's period."""
        with self._lock:
            armed = self._armed
        if interlock.armed_only and not armed:
            return
        reason = interlock.decide(value)
        if reason is not None:
            self._tripped(interlock.name, reason, interlock.latched)

    def emcy(self, interlock: DeviceFault, code: int) -> None:
        """EMCY callback path (CAN receive thread)."""
        reason = interlock.on_emcy(code)
        if reason is not None:
            self._tripped(interlock.name, interlock.reason or reason, latched=True)

    def _tripped(self, name: str, reason: str, latched: bool) -> None:
        trip = Trip(
            name, reason, latched, datetime.now(timezone.utc).isoformat(timespec="milliseconds"), time.monotonic()
        )
        with self._lock:
            new_for_run = self._armed and self._run_trip is None
            if new_for_run:
                self._run_trip = trip
            same = self._reported.get(name) == reason
            if not same:
                self._reported[name] = reason
                self._last_trip = trip
        if new_for_run or not same:
            log.warning("interlock %s tripped: %s", name, reason)
            try:
                self.on_trip(trip)
            except Exception:  # noqa: BLE001 - reporting must not stop the watch
                log.exception("on_trip failed")

    # --- refusal and acknowledgement --------------------------------------------------------------------
    def refusal(self) -> Trip | None:
        """The interlock that forbids starting a run or commanding torque now (None: clear to go).
        Decided from a fresh reading of every interlock that is not armed-only."""
        now = time.monotonic()
        for lock in self.interlocks:
            if lock.armed_only:
                continue
            reason = lock.evaluate()
            if reason is not None:
                return Trip(
                    lock.name, reason, lock.latched, datetime.now(timezone.utc).isoformat(timespec="milliseconds"), now
                )
        return None

    def reset_latched(self) -> Trip | None:
        """After a person's fault reset: clear latched trips whose condition has gone; returns what
        still forbids a run (None: clear)."""
        for lock in self.interlocks:
            if lock.latched:
                lock.reset()
        with self._lock:
            self._last_trip = None
            self._reported.clear()
        return self.refusal()

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            run_trip, last = self._run_trip, self._last_trip
        return {
            "tripped": [
                {"interlock": lock.name, "reason": lock.reason, "latched": lock.latched}
                for lock in self.interlocks
                if lock.reason is not None
            ],
            "run_trip": run_trip.public() if run_trip else None,
            "last_trip": last.public() if last else None,
        }
