"""`ripplecal serve`'s uvicorn server: how SIGINT and SIGTERM stop it, bench safe, in bounded time.

A signal handler runs in the main thread between two bytecodes, wherever that thread is: also inside a
lock it holds, or inside the handler of the signal before (a terminal's Ctrl+C reaches `make run` and
the service both, and make forwards what it got to its child: two signals within milliseconds). So the
handler here only records and sets flags, and wakes the backstop thread through a pipe (a write to a
non-blocking pipe: no lock). That thread asks the bench to stop at once (`stop_bench_now`: the bench
watchdog disables drive and load whatever the worker is doing). The event loop does the rest on its
next tick (0.1 s): it ends the open event streams (uvicorn waits for open connections before the app's
shutdown runs), and the app's shutdown stops the service, which leaves the bench safe (drive and load
disabled, heartbeat consumers disarmed).

A second signal, SIGINT or SIGTERM (uvicorn forces only on a second SIGINT), forces the exit: uvicorn
stops waiting for connections and tasks. It would also skip the app's shutdown; that shutdown is what
makes the bench safe, so it runs all the same. Should the shutdown itself not end, the backstop thread
ends the process (`os._exit`) FORCED_EXIT_S after the second signal, or UNFORCED_EXIT_S after a single
one: an unorderly end, after which the drive's heartbeat consumer takes its torque off (a FAULT that the
next start names)."""

from __future__ import annotations

import os
import select
import signal
import threading
import time
from typing import cast

import uvicorn

# after a second signal: the orderly stop takes 0.5-2 s (6.7 s seen on 2 cores under load 8), the drive's
# power stage is off within 0.01 s of the first signal (the watchdog); 10 s is the promise
FORCED_EXIT_S = 8.0
UNFORCED_EXIT_S = 30.0  # after a single signal: the service's own stop is bounded well below this


class ServiceServer(uvicorn.Server):
    """uvicorn's server stopping `service` on signals (module doc). `service`: a CalibrationService (its
    `shutdown_reason` names the signal in the sweeps it interrupts, its `broker` the event streams)."""

    def __init__(
        self,
        config: uvicorn.Config,
        service,
        forced_exit_s: float = FORCED_EXIT_S,
        unforced_exit_s: float = UNFORCED_EXIT_S,
    ):
        super().__init__(config)
        self.service = service
        self.forced_exit_s = forced_exit_s
        self.unforced_exit_s = unforced_exit_s
        self.signals: list[int] = []  # as they came (appended in the handler: no lock)
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_write, False)  # a full pipe never blocks the handler: the thread is awake
        self._backstop = threading.Thread(target=self._backstop_run, name="ripplecal-exit-backstop", daemon=True)

    async def serve(self, sockets=None) -> None:
        self._backstop.start()  # before uvicorn installs the handlers that wake it
        await super().serve(sockets)

    def handle_exit(self, sig: int, frame) -> None:
        """The signal handler: flags and a wake, nothing that takes a lock or waits (module doc)."""
        # written so that a second signal's handler run inside this one (Python nests them) leaves the
        # same result: the first signal names the shutdown, any second one forces it
        self.signals.append(sig)
        self.service.shutdown_reason = f"service shut down ({signal.Signals(self.signals[0]).name})"
        if len(self.signals) >= 2:
            self.force_exit = True  # uvicorn's own forced exit, for SIGTERM as for SIGINT
        super().handle_exit(sig, frame)  # uvicorn's flags, and the signal raised again once it has stopped
        try:
            os.write(self._wake_write, b"s")
        except OSError:  # the pipe is full: the backstop has a wake pending already
            pass

    async def shutdown(self, sockets=None) -> None:
        # in the event loop, not the handler: the streams end first, or uvicorn waits for them
        self.service.broker.close()
        await super().shutdown(sockets)
        # uvicorn skips the app's shutdown on a forced exit: it is what leaves the bench safe, so it runs
        stopped = getattr(self.lifespan, "shutdown_event", None)
        if self.force_exit and stopped is not None and not stopped.is_set():
            await self.lifespan.shutdown()

    def _backstop_run(self) -> None:
        """Ends the process if its stop does not end in time (module doc). Waits on the pipe only."""
        first_at = second_at = None
        while True:
            deadlines: list[float] = []
            if first_at is not None:
                deadlines.append(first_at + self.unforced_exit_s)
            if second_at is not None:
                deadlines.append(second_at + self.forced_exit_s)
            timeout_s = max(0.0, min(deadlines) - time.monotonic()) if deadlines else None
            ready, _, _ = select.select([self._wake_read], [], [], timeout_s)
            if ready:
                os.read(self._wake_read, 64)
                now = time.monotonic()
                count = len(self.signals)
                if count >= 1 and first_at is None:
                    first_at = now
                    # the bench safe at once, before connections drain and the app's shutdown runs (a worker
                    # stuck on the database would otherwise hold it at torque); a flag and a wake, no I/O here
                    stop_bench_now = getattr(self.service, "stop_bench_now", None)
                    try:
                        if stop_bench_now is not None:
                            stop_bench_now()
                    except Exception as exc:  # noqa: BLE001 - this thread must live on: it is the bound
                        os.write(2, f"ripplecal: stopping the bench at once failed: {exc!r}\n".encode())
                if count >= 2 and second_at is None:
                    second_at = now
                continue
            if deadlines and time.monotonic() >= min(deadlines):
                self._exit_now(first_at, second_at)

    def _exit_now(self, first_at: float | None, second_at: float | None) -> None:
        """The stop did not end: out now. Written straight to stderr (no logging lock: the stuck thread
        may hold it)."""
        # a deadline passed, so a signal came: first_at is set (a cast, never an assert on the way out)
        waited_s = time.monotonic() - cast(float, second_at if second_at is not None else first_at)
        after = "the second signal" if second_at is not None else "the signal"
        message = (
            f"ripplecal: the service did not stop within {waited_s:.0f} s of {after}: exiting now, unorderly; "
            "the drive's and load's heartbeat consumers take their torque off (FAULT): check the bench and "
            "reset the fault (POST /api/v1/bench/fault-reset) at the next start\n"
        )
        try:
            os.write(2, message.encode())
        finally:
            os._exit(128 + (self.signals[0] if self.signals else signal.SIGTERM))
