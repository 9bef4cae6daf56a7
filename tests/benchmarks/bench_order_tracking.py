"""Computed order tracking of a run-up (run: python -m tests.benchmarks.bench_order_tracking).

A 16 s ramp 1000 -> 2600 rpm at 16 kHz (4 pole pairs, tests/support/runup_ramp.py) analysed by
service.model.order_tracking.track_orders for orders 1..48 in 10 rpm bins, on one BLAS thread as the
service runs; prints the best wall time of three against the ramp's own 16 s (a run-up's analysis
must be well under the time the ramp takes) and the same with the shaft mode as a nuisance.
"""

from __future__ import annotations

import math
import time

from drivers.blas_threads import one_blas_thread
from service.model.demodulation import ResonanceMode
from service.model.order_tracking import track_orders
from tests.support.runup_ramp import POLE_PAIRS, RATE_HZ, ramp_record

RAMP_S = 16.0
ORDERS = list(range(1, 49))


def main() -> None:
    one_blas_thread()
    angle, alpha = ramp_record(1000.0, 2600.0, {6: (0.1, 30.0), 12: (0.1, -120.0)}, 0.01, duration_s=RAMP_S)
    mode = ResonanceMode(sigma_rad_s=-1.0 / 0.051, omega_rad_s=2 * math.pi * 1074.0)
    for label, shaft_mode in (("orders 1..48", None), ("orders 1..48 + shaft mode", mode)):
        best = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            track = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, ORDERS, mode=shaft_mode)
            best = min(best, time.perf_counter() - t0)
        print(
            f"{label}: {len(angle)} samples ({RAMP_S:g} s ramp), {int(track.windows.sum())} windows, "
            f"{len(track.speed_rpm)} bins: {best:.2f} s ({best / RAMP_S:.1%} of the ramp's time)"
        )


if __name__ == "__main__":
    main()
