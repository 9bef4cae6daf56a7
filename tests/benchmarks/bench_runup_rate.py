"""A refined LUT along run-ups through the turn at different ramp rates and directions (issue 27).

Run: python -m tests.benchmarks.bench_runup_rate [--torque 1.0] [--seed N]

On the emulated bench (speedup 0): the 4 x 5 probe sweep of bench_runup_refinement, refined (placement from curves,
int11 cells, 2048 bytes; validated at grid points and midpoints only), then run-ups over 2050..2350 rpm at one
torque, without and with the drive's LUT, at 200 rpm/s up and down and at 12.5 rpm/s up. Printed per ramp: each
10-rpm bin's suppression of the 6th (dB, the uncompensated over the LUT's residual). A bin that fails at every rate
and direction is the LUT between its breakpoints; one that fails only on the fast ramp is the drive's state lagging
the ramp (the LUT holds it in steady state).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

from service.calibration_service import CalibrationService
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.runs.refinement import RefineRequest
from service.runs.runup import RunupRequest
from service.runs.validation import ValidationOptions
from service.settings import load_settings
from tests.support.waiting import wait_run_finished

GRID = Grid(torque_nm=[1, 2, 3, 4], speed_rpm=[1000, 1400, 1800, 2200, 2600], udc_v=[12])
RAMPS = ((200.0, "up"), (200.0, "down"), (12.5, "up"))  # (rpm/s, direction)
SPEED_RANGE_RPM = (2050.0, 2350.0)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--torque", type=float, default=1.0, help="the run-ups' torque, Nm")
    parser.add_argument("--seed", type=int, default=None, help="a seeded machine; default paper-bench")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        overrides: dict = {"emulator.speedup": 0.0, "server.db_path": str(Path(tmp) / "r.db")}
        if args.seed is not None:
            overrides["emulator.seed"] = args.seed
        with CalibrationService(load_settings(environ={}, overrides=overrides)) as svc:
            svc.start(status_period_s=None)
            sweep_id = svc.engine.submit_sweep(GRID, "probe", parse_options("probe", {}))
            sweep = wait_run_finished(lambda: svc.storage.get_sweep(sweep_id), 3600.0, "sweep")
            request = RefineRequest(
                target_db=30,
                max_cells=1000,
                max_bytes=2048,
                placement="curves",
                lut_cells="int11",
                validation=ValidationOptions(runups=False),
            )
            job_id = svc.engine.submit("refinement", sweep["map_id"], request)
            job = wait_run_finished(lambda: svc.storage.get_job(job_id), 7200.0, "refinement")
            print(f"refinement {job['state']}; the drive holds its last map's LUT; {args.torque:g} Nm at 12 V")
            for rate, direction in RAMPS:
                results = {}
                for injection in ("off", "lut"):
                    req = RunupRequest(
                        torque_nm=args.torque,
                        udc_v=12,
                        speed_rpm=SPEED_RANGE_RPM,
                        rate_rpm_per_s=rate,
                        direction=direction,
                        injection=injection,
                    )
                    runup_job = svc.engine.submit("runup", req)
                    wait_run_finished(lambda j=runup_job: svc.storage.get_job(j), 600.0, "run-up")
                    results[injection] = (svc.storage.runup_of_job(runup_job) or {})["result"]
                off, lut = results["off"], results["lut"]
                k = off["orders"].index(6)
                residual = dict(zip(lut["speed_rpm"], lut["amplitude"][k]))
                bins = [
                    f"{speed:.0f}:{20 * math.log10(a / residual[speed]):.0f}"
                    for speed, a in zip(off["speed_rpm"], off["amplitude"][k])
                    if a and residual.get(speed)
                ]
                print(f"  {rate:g} rpm/s {direction}: " + " ".join(bins))


if __name__ == "__main__":
    main()
