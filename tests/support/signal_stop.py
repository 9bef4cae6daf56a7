"""Two signals in quick succession to `ripplecal serve` (or to `make run`'s process group, as a terminal's
Ctrl+C reaches make and the service both), how long the service took to end, and the bench it left
(read through the emulator's control socket: the service is gone by then). Used by
tests/e2e/test_signals_e2e.py (a few tries) and tests/benchmarks/bench_shutdown.py (20 of each kind)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from tests.support.bench_rig import alive, children_of, served_bench
from tests.support.waiting import wait_until

STOP_BOUND_S = 10.0  # issue 25: two signals end the service within this, bench safe
SIGNAL_GAP_S = 0.05  # between the two signals
# a sweep long enough at --speedup 1 that it is still at torque when the signals come
SWEEP = {"grid": {"torque_nm": [1.0, 2.5], "speed_rpm": [1000, 1500], "udc_v": [48]}, "method": "probe"}


@dataclass
class StopOutcome:
    ended_s: float | None  # from the first signal to the process's end (None: not within the wait)
    exit_code: int | None
    drive: dict  # the emulator's drive and load as the service left them
    log: str
    power_off_s: float | None = None  # from the first signal to the drive's power stage off (None: was off)

    @property
    def safe(self) -> bool:
        """Drive and load not enabled, and left as an orderly stop leaves them: not in FAULT, their
        heartbeat consumers disarmed (the next start needs no fault reset)."""
        d = self.drive
        return (
            d["drive_state"] not in ("operation_enabled", "fault")
            and d["load_state"] not in ("operation_enabled", "fault")
            and d["drive_heartbeat_consumer_ms"] == 0
            and d["load_heartbeat_consumer_ms"] == 0
        )

    def within_bound(self) -> bool:
        return self.ended_s is not None and self.ended_s <= STOP_BOUND_S

    def describe(self) -> str:
        keys = ("drive_state", "load_state", "drive_torque_nm", "drive_heartbeat_consumer_ms")
        return f"ended after {self.ended_s} s (exit {self.exit_code}); " + ", ".join(
            f"{k}={self.drive.get(k)}" for k in keys
        )


def send_twice(pid: int, sig: int, group: bool = False, gap_s: float = SIGNAL_GAP_S) -> float:
    """`sig` to the process (or its process group), twice `gap_s` apart; the monotonic time of the first."""
    send = os.killpg if group else os.kill
    first = time.monotonic()
    send(pid, sig)
    time.sleep(gap_s)
    send(pid, sig)
    return first


def wait_ended(proc: subprocess.Popen, since: float, wait_s: float) -> float | None:
    """Seconds from `since` to the end of `proc`; None if it has not ended `wait_s` after `since`."""
    try:
        proc.wait(timeout=max(0.0, since + wait_s - time.monotonic()))
    except subprocess.TimeoutExpired:
        return None
    return time.monotonic() - since


def emulator_state(emu) -> dict:
    return emu.control({"status": True})["faults"]


def at_torque(emu) -> bool:
    state = emulator_state(emu)
    return state["drive_state"] == "operation_enabled" and abs(state["drive_torque_nm"]) > 0.5


def serve_try(directory: Path, sig: int, mid_sweep: bool, wait_s: float = 30.0) -> StopOutcome:
    """`ripplecal serve --bench` on its own emulated bench at --speedup 1, idle or with a sweep at torque,
    then `sig` twice."""
    with served_bench(directory, "ripplecal.db", speedup=1.0) as (emu, svc, api, _db):
        if mid_sweep:
            r = api.post("/sweeps", SWEEP)
            assert r.status_code == 202, r.text
            wait_until(lambda: at_torque(emu), 90, "the sweep's drive at torque", poll_s=0.1)
        first = send_twice(svc.proc.pid, sig)
        ended_s = wait_ended(svc.proc, first, wait_s)
        state = emulator_state(emu)
        exit_code = svc.proc.poll()
    # the emulator's monotonic clock is the system's (CLOCK_MONOTONIC), as this process's
    off_at = state.get("drive_power_off_at")
    power_off_s = off_at - first if off_at is not None and off_at >= first else None
    return StopOutcome(ended_s, exit_code, state, svc.log_text(), power_off_s)


def process_tree(pid: int) -> list[int]:
    """`pid` and its descendants (an emulator child in its own session too)."""
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        found.append(p)
        todo += children_of(p)
    return found


def left_running(pids: list[int], wait_s: float = 5.0) -> list[int]:
    """Which of `pids` still run after up to `wait_s`."""
    deadline = time.monotonic() + wait_s
    while (running := [p for p in pids if alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return running


def group_signal_twice(proc: subprocess.Popen, sig: int, wait_s: float = 30.0) -> tuple[float | None, list[int]]:
    """`sig` twice to the process group of `proc` (started with start_new_session: make and its service);
    (seconds to the end of `proc`, the processes of its tree still running then)."""
    tree = process_tree(proc.pid)
    first = send_twice(proc.pid, sig, group=True)
    ended_s = wait_ended(proc, first, wait_s)
    return ended_s, left_running(tree, 0.0 if ended_s is None else 2.0)


def signal_name(sig: int) -> str:
    return signal.Signals(sig).name
