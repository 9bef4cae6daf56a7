"""A run-up's cost and truth (issue 27): wall time against its ramp at speedup 1, and its order cut against
separate stepped measurements at the same speeds.

Run: python -m tests.benchmarks.bench_runup [--speedup 1] [--seed N] [--rate 100]

On the emulated bench (paper-bench, or a seeded machine): a run-up of 1000 -> 2600 rpm at 100 rpm/s, 2.5 Nm,
12 V, injection off, orders 6 and 12 (service/runs/runup.py); then, in one run per order, the uncompensated
phasor of that order measured standing at each of 9 speeds (identification.common.measure_reference: known
to 1 % of itself). Printed: wall seconds of the run-up against its ramp's 16 s (target <= 1.3 x), and per
speed and order the run-up bin's level, the stepped level and their difference in dB, judged where the
order stands >= 20 dB above the bin's noise floor (target: within 1 dB).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from service.calibration_service import CalibrationService
from service.identification.common import measure_reference
from service.model.operating_point import OperatingPoint
from service.runs.runup import RunupRequest, runup_in_run
from service.settings import load_settings

STEPPED_RPM = [1100, 1300, 1500, 1700, 1900, 2100, 2300, 2450, 2550]


def db(x: float) -> float:
    return 20.0 * math.log10(x)


def stepped_levels(svc: CalibrationService, order: int, torque_nm: float, udc_v: float) -> dict[float, float]:
    """The order's uncompensated amplitude (fs) standing at each speed, in one run."""
    levels = {}
    with svc.bench.run(order) as run:
        for speed in STEPPED_RPM:
            with run.operating_point(OperatingPoint(torque_nm=torque_nm, speed_rpm=speed, udc_v=udc_v)) as session:
                window = measure_reference(session, 64, 256)  # <= 0.6 s a read: the watchdog bound is 3 s
            levels[speed] = window.phasor.amplitude
    return levels


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--speedup", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--rate", type=float, default=100.0)
    args = parser.parse_args()
    overrides: dict = {"emulator.speedup": args.speedup}
    if args.seed is not None:
        overrides["emulator.seed"] = args.seed
    with tempfile.TemporaryDirectory() as tmp:
        overrides["server.db_path"] = str(Path(tmp) / "runup.db")
        settings = load_settings(environ={}, overrides=overrides)
        with CalibrationService(settings) as svc:
            req = RunupRequest(
                torque_nm=2.5, udc_v=12, speed_rpm=(1000, 2600), rate_rpm_per_s=args.rate, orders=[6, 12]
            )
            t0 = time.perf_counter()
            result = runup_in_run(svc.bench, settings, req, None)
            wall_s = time.perf_counter() - t0
            ramp_s = req.ramp_s()
            print(
                f"run-up 1000 -> 2600 rpm at {args.rate:g} rpm/s (speedup {args.speedup:g}, seed {args.seed}): "
                f"wall {wall_s:.2f} s for a {ramp_s:.1f} s ramp = {wall_s / ramp_s:.2f} x (target <= 1.3 x at speedup 1); "
                f"plant {result['plant_time_s']:.2f} s, {len(result['speed_rpm'])} bins"
            )
            worst, judged = 0.0, 0
            for k, order in enumerate(result["orders"]):
                stepped = stepped_levels(svc, order, req.torque_nm, req.udc_v)
                for speed, level in stepped.items():
                    i = result["speed_rpm"].index(float(speed))
                    cut, floor = result["amplitude"][k][i], result["noise_floor"][i]
                    above = db(cut) - db(floor)
                    diff = db(cut) - db(level)
                    held = above >= 20.0
                    if held:
                        judged += 1
                        worst = max(worst, abs(diff))
                    print(
                        f"  order {order:2d} {speed:5.0f} rpm: run-up {db(cut):6.1f} dB fs, stepped {db(level):6.1f}, "
                        f"diff {diff:+5.2f} dB, {above:5.1f} dB above floor{'' if held else ' (not judged)'}"
                    )
            print(f"order cut vs stepped: worst {worst:.2f} dB over {judged} judged points (target <= 1 dB)")


if __name__ == "__main__":
    main()
