"""The DAQ frame-rate check at connect: what it measures and what it costs
(run: python -m tests.benchmarks.bench_daq_rate).

DaqReader.check_frame_rate against (a) a real pty that a writer thread fills at 16 kHz on the wall
clock, 2 ms of frames per write, as a DAQ streams; (b) the emulator at --speedup 1 (its paced DAQ);
(c) the emulator at --speedup 0, which streams as fast as it is read (the check must not judge it: its
measured rate must stay far above FREE_RUNNING_RATIO x 16 kHz). Printed per source: the measured rate
(min / median / max over the tries), the largest relative error, and the wall time one check costs.
The thresholds (FRAME_RATE_TOLERANCE, FREE_RUNNING_RATIO) are set with margins over these.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from drivers import daq_reader
from drivers.daq_protocol import FRAME_BYTES, encode_frames
from drivers.daq_reader import DaqReader
from tests.support.bench_rig import EmulatorRig
from tests.support.pty_writer import PtyWriter

RATE_HZ = 16_000
TRIES = 8


def _checks(url: str, expected_hz: float) -> list[tuple[float, float, bool]]:
    """(measured Hz, wall s, judged) per try, a fresh reader each time as at connect."""
    out = []
    for _ in range(TRIES):
        with DaqReader(url, max_buffered_samples=4096) as reader:
            t0 = time.monotonic()
            check = reader.check_frame_rate(expected_hz, first_frame_timeout_s=5.0)
            out.append((check.measured_hz, time.monotonic() - t0, check.judged))
    return out


def _print(source: str, results: list[tuple[float, float, bool]], expected_hz: float) -> None:
    rates = [r for r, _, _ in results]
    walls = [w for _, w, _ in results]
    worst = max(abs(r / expected_hz - 1) for r in rates)
    judged = sum(j for _, _, j in results)
    print(
        f"{source:38s} measured {min(rates):10.0f} / {statistics.median(rates):10.0f} / {max(rates):10.0f} "
        f"frames/s (min/median/max of {len(rates)}), worst error {worst:7.1%}, judged {judged}/{len(rates)}, "
        f"check costs {statistics.median(walls):.2f} s (max {max(walls):.2f} s)"
    )


def paced_pty() -> None:
    writer = PtyWriter()
    try:
        seconds = TRIES * 2 * (daq_reader.FRAME_RATE_SETTLE_S + daq_reader.FRAME_RATE_WINDOW_S) + 5
        n = int(seconds * RATE_HZ)
        zeros = np.zeros(n, dtype=np.int64)
        data = encode_frames(np.arange(n), zeros, zeros, zeros)
        writer.write_at_rate(data, 32 * FRAME_BYTES, RATE_HZ * FRAME_BYTES)
        _print("pty paced at 16 kHz", _checks(writer.path, RATE_HZ), RATE_HZ)
    finally:
        writer.close()


def emulator(speedup: float) -> None:
    rig = EmulatorRig(speedup=speedup)
    try:
        rate = rig.endpoints["sample_rate_hz"]
        _print(f"emulator at --speedup {speedup:g}", _checks(rig.endpoints["daq"], rate), rate)
    finally:
        rig.stop()


def main() -> None:
    print(
        f"tolerance +-{daq_reader.FRAME_RATE_TOLERANCE:.0%}, free running above "
        f"{daq_reader.FREE_RUNNING_RATIO:g} x the expected rate"
    )
    paced_pty()
    emulator(1.0)
    emulator(0.0)


if __name__ == "__main__":
    main()
