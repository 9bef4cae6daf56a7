"""Two signals in quick succession (run: python -m tests.benchmarks.bench_shutdown [--tries N], or `make bench`).

`ripplecal serve --bench FILE` on its own emulated bench at --speedup 1, idle or mid-sweep with the drive at
torque, gets SIGINT twice or SIGTERM twice 50 ms apart (tests/support/signal_stop.py). Per kind (20 tries
each by default) it prints: the tries that ended within 10 s with the bench safe (drive and load
disabled, not in FAULT, heartbeat consumers disarmed), the median and worst time from the first signal
to the end of the process, and mid-sweep the worst time from the first signal to the drive's power stage
off (the emulator's side; CLOCK_MONOTONIC is system-wide). Issue 25 asks 20 of 20 in each kind."""

from __future__ import annotations

import argparse
import signal
import statistics
import sys
import tempfile
from pathlib import Path

from tests.support.signal_stop import SIGNAL_GAP_S, STOP_BOUND_S, serve_try

KINDS = [
    ("idle", False, signal.SIGINT),
    ("idle", False, signal.SIGTERM),
    ("mid-sweep", True, signal.SIGINT),
    ("mid-sweep", True, signal.SIGTERM),
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tries", type=int, default=20, help="tries of each kind (default 20)")
    args = parser.parse_args()
    all_good = True
    with tempfile.TemporaryDirectory(prefix="bench-shutdown-") as tmp:
        print(f"two signals {SIGNAL_GAP_S * 1000:.0f} ms apart; bound {STOP_BOUND_S:g} s; {args.tries} tries per kind")
        for name, mid_sweep, sig in KINDS:
            ended, power_off, bad = [], [], []
            for i in range(args.tries):
                directory = Path(tmp) / f"{name}-{sig.name}-{i}"
                directory.mkdir()
                try:
                    outcome = serve_try(directory, sig, mid_sweep)
                except (RuntimeError, TimeoutError, AssertionError) as exc:  # a try that did not get to the signals
                    bad.append(f"try {i + 1}: did not get to the signals: {str(exc).splitlines()[0][:300]}")
                    continue
                if outcome.ended_s is not None:
                    ended.append(outcome.ended_s)
                if outcome.power_off_s is not None:
                    power_off.append(outcome.power_off_s)
                if not (outcome.within_bound() and outcome.safe):
                    bad.append(f"try {i + 1}: {outcome.describe()}")
            good = args.tries - len(bad)
            all_good &= not bad
            times = f"end median {statistics.median(ended):.2f} s, worst {max(ended):.2f} s" if ended else "none ended"
            off = f"; signal to power stage off worst {max(power_off):.2f} s" if power_off else ""
            print(f"{name:9} {sig.name}x2: {good}/{args.tries} ended safe within {STOP_BOUND_S:g} s; {times}{off}")
            for line in bad:
                print(f"    {line}")
            sys.stdout.flush()
    return 0 if all_good else 1


if __name__ == "__main__":
    sys.exit(main())
