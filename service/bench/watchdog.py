"""The bench watchdog: the bench made safe without waiting on the worker, storage or the network.

A run's loop kicks the watchdog (every guard check, before each DAQ read, every SDO transfer its thread
gets answered, and while it waits for the supply). While a run is armed, a loop silent for `bound_s` of wall time (the worker stuck: a database
that hangs, a lock, a bug) makes the watchdog's own thread disable drive and load at once: the drivers'
disable (torque 0, injection off, power stage off), then the load braked on its own speed loop and
disabled. A stop asked from outside (a cancel, a shutdown, a signal) disables the drive at once and
commands the load to standstill, leaving it enabled to brake: the run's own make_safe disables it at
standstill (a load disabled at speed coasts, and a next run would meet a turning shaft); if that run then
goes silent for `bound_s`, the load is braked and disabled here too. It takes none of the locks
the worker may hold (the bench's run lock); the drivers serialise single SDO transfers only, each
bounded by the SDO timeout. The run then ends at its next guard (`tripped`), and the stop is logged
and reported (`on_stop`, the service's SSE) with why.

`request_stop` only sets a flag and wakes the thread: it is safe from a signal handler or an HTTP
request, and never blocks.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from drivers.drive import DriveClient
from drivers.load_machine import LoadClient
from service.bench.standstill import StandstillJudge
from service.bench.trips import Trip

log = logging.getLogger(__name__)

_OUR_CODE = str(Path(__file__).resolve().parents[2])  # a stall names the innermost frame of the project's code

PERIOD_S = 0.05  # how often the watchdog looks at the run's last kick
STANDSTILL_TIMEOUT_S = 3.0  # the load is disabled at standstill or after this long braking (wall clock)


class BenchWatchdog:
    """Disables drive and load when an armed run stops kicking or a stop is asked (module doc).
    `drive()` / `load()`: the current driver objects (None when not connected); `on_stop(trip)`: the
    service's reporter, called from the watchdog's thread after the bench is safe."""

    def __init__(
        self,
        drive: Callable[[], DriveClient | None],
        load: Callable[[], LoadClient | None],
        bound_s: float,
        on_stop: Callable[[Trip], None] | None = None,
    ):
        self._drive = drive
        self._load = load
        self.bound_s = bound_s
        self.on_stop = on_stop
        self._armed = False
        self._last_kick = time.monotonic()
        self._asked: str | None = None  # why a stop was asked from outside (cancel, shutdown)
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._safe = threading.Event()  # set once a stop has disabled drive and load (or none was needed)
        self._safe.set()
        self.tripped: Trip | None = None  # the stop of the current run (None: none)
        self._load_braking = False  # a stop asked left the load braking, for the run's make_safe to disable
        self.last_stop: Trip | None = None  # the latest stop, kept for the status until the next one
        # time.monotonic() (system-wide CLOCK_MONOTONIC) of the run's last kick before a stop for silence
        self.silent_since_monotonic: float | None = None
        self._worker: int | None = None  # the thread that armed the run
        self._thread: threading.Thread | None = None

    # --- the run's side (the worker) ---------------------------------------------------------------------
    def arm(self) -> None:
        """A run starts: watched from now on."""
        self.tripped = None
        self._load_braking = False
        self._asked = None
        self._last_kick = time.monotonic()
        self._worker = threading.get_ident()  # whose stack a stall names
        self._armed = True

    def kick(self) -> None:
        """The run's loop is alive."""
        self._last_kick = time.monotonic()

    def bus_answered(self) -> None:
        """A device answered an SDO transfer: from the armed run's own thread that is its loop at work (one
        move may take many transfers, each bounded by the SDO timeout, on a slow bus), so it counts as a kick.
        Answers to other threads (the status poll) say nothing of the run."""
        if self._armed and threading.get_ident() == self._worker:
            self._last_kick = time.monotonic()

    def disarm(self) -> Trip | None:
        """The run has ended (made safe by its own make_safe); the watchdog's stop of it, if any."""
        self._armed = False
        self._load_braking = False
        return self.tripped

    # --- from outside (routes, shutdown, signal handlers) -------------------------------------------------
    def request_stop(self, reason: str) -> None:
        """Disable drive and load now if a run is armed (no lock, no I/O here: the watchdog's thread acts)."""
        if self._armed and self._asked is None:
            self._asked = reason
            self._safe.clear()
        self._wake.set()

    def wait_safe(self, timeout_s: float) -> bool:
        """After request_stop: True once the watchdog's stop has run (or none was needed)."""
        return self._safe.wait(timeout_s)

    # --- the thread ----------------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._watch, name="ripplecal-bench-watchdog", daemon=True)
            self._thread.start()

    def close(self) -> None:
        self._closed.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)

    def _watch(self) -> None:
        while not self._closed.is_set():
            self._wake.wait(PERIOD_S)
            self._wake.clear()
            try:
                self._look()
            except Exception:  # noqa: BLE001 - the watchdog must outlive any one bad round
                log.exception("bench watchdog round failed")

    def _look(self) -> None:
        if not self._armed:
            self._safe.set()
            return
        silent_s = time.monotonic() - self._last_kick
        if self.tripped is not None:
            # a stop asked left the load braking for the run's own make_safe; a run that then goes silent
            # (its worker stuck) has the load braked and disabled here
            if self._load_braking and silent_s > self.bound_s:
                self._load_braking = False
                log.error(
                    "the run did not end after its stop: the load is disabled by the bench watchdog (%s)",
                    self._stop_load(),
                )
            self._safe.set()
            return
        if self._asked is not None:
            reason = f"{self._asked}: torque off at once by the bench watchdog, the load braked to standstill"
            kind = "stop_asked"
            self.silent_since_monotonic = None
        elif silent_s > self.bound_s:
            self.silent_since_monotonic = self._last_kick
            stack = self._worker_stack()
            ours = [f for f in stack if f.filename.startswith(_OUR_CODE) and "site-packages" not in f.filename]
            at = (ours or stack)[-1] if stack else None
            where = f" at {Path(at.filename).name}:{at.lineno} in {at.name}" if at is not None else ""
            reason = (
                f"the run's loop did not report for {silent_s:.1f} s (bound {self.bound_s:g} s; the worker is "
                f"stuck{where}, e.g. waiting for the database): drive and load disabled by the bench watchdog"
            )
            # where the worker was when it went silent: what a person needs to find why
            log.error("the stalled run's worker, innermost last:\n%s", "".join(traceback.format_list(stack)))
            kind = "stalled"
        else:
            return
        trip = Trip(
            "bench_watchdog",
            reason,
            latched=False,
            at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            monotonic=time.monotonic(),
        )
        self.tripped = self.last_stop = trip
        if kind == "stop_asked":
            # torque off now; the load brakes on its speed loop, and the run's make_safe (which reads the DAQ, so
            # the plant's clock moves) disables it at standstill: a load disabled at speed coasts
            outcome = self._disable_drive_brake_load()
            self._load_braking = True
        else:
            outcome = self._disable_all()
        (log.warning if kind == "stop_asked" else log.error)("%s (%s)", reason, outcome)
        self._safe.set()
        if self.on_stop is not None:
            try:
                self.on_stop(trip)
            except Exception:  # noqa: BLE001 - a reporter that fails must not undo the stop
                log.exception("bench watchdog: reporting the stop failed")

    def _worker_stack(self) -> traceback.StackSummary:
        """The armed run's thread's stack now (empty when that thread is gone)."""
        frame = sys._current_frames().get(self._worker) if self._worker is not None else None
        return traceback.extract_stack(frame) if frame is not None else traceback.StackSummary()

    def _disable_all(self) -> str:
        """Drive first (its torque is what hurts), then the load braked on its speed loop and disabled.
        Every step is tried; returns what happened, for the log."""
        failed = self._drive_off()
        failed += self._load_off()
        return "bench made safe" if not failed else "not every step succeeded: " + "; ".join(failed)

    def _disable_drive_brake_load(self) -> str:
        """Drive disabled, the load commanded to standstill on its speed loop (left enabled to brake)."""
        failed = self._drive_off()
        load = self._load()
        if load is not None:
            try:
                load.brake_to_standstill()
            except Exception as exc:  # noqa: BLE001 - the drive is off; the stall path disables the load
                failed.append(f"load braking: {exc}")
        return "torque off, load braking" if not failed else "not every step succeeded: " + "; ".join(failed)

    def _stop_load(self) -> str:
        failed = self._load_off()
        return "load stopped" if not failed else "not every step succeeded: " + "; ".join(failed)

    def _drive_off(self) -> list[str]:
        drive = self._drive()
        if drive is None:
            return []
        try:
            drive.disable()
        except Exception as exc:  # noqa: BLE001 - the load is stopped whatever the drive says
            return [f"drive: {exc}"]
        return []

    def _load_off(self) -> list[str]:
        """The load braked on its speed loop (bounded, wall clock), then disabled either way."""
        load, failed = self._load(), list[str]()
        if load is None:
            return failed
        try:
            load.brake_to_standstill()
            deadline, judge = time.monotonic() + STANDSTILL_TIMEOUT_S, StandstillJudge()
            while time.monotonic() < deadline and not judge.update(time.monotonic(), load.read_status().speed_rpm):
                time.sleep(0.02)
        except Exception as exc:  # noqa: BLE001 - disabled below either way
            failed.append(f"load braking: {exc}")
        try:
            load.disable()
        except Exception as exc:  # noqa: BLE001
            failed.append(f"load: {exc}")
        return failed
