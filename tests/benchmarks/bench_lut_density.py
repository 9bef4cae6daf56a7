"""How dense a LUT must be to hold across the field-weakening turn (issue 17's figure, measured): theta*
identified every `--step-rpm` along speed at three torques, then the fewest speed breakpoints per torque
row for which the drive's own interpolation (drivers.lut_image.Lut.theta, polar and cartesian) holds
`--target-db` at every scanned speed between them (greedy from the low end: each breakpoint as far as
the next one can go; optimal for a 1-D row). Run: python -m tests.benchmarks.bench_lut_density
[--seeds None,1] [--step-rpm 10] [--target-db 30].

Why it matters: LUT-mode suppression at a point is 20 log10 |theta*| / |theta_lut - theta*| (the
residual is S (theta_lut - theta*), eq. 8, and the uncompensated harmonic is -S theta*), so 30 dB asks the
interpolated theta to be within 3.2 % of theta*, i.e. within 1.8 deg in phase. Past the onset of field
weakening theta* turns by up to ~3 deg/rpm (a spiral, the point where the harmonic's own phasor passes
near zero), so no placement of cells reaches that with a few breakpoints. Printed: per row the count and
the breakpoints; the fewest values of one speed axis that holds every row (a LUT is a full grid) and
the cells that puts in a LUT with the 5 x 5 map's torque rows, against 2.5 x its cells.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from drivers.lut_image import FLAG_OK, INTERPOLATIONS, Lut
from service.calibration_service import CalibrationService
from service.model.limits import EnvelopeError
from service.model.operating_point import OperatingPoint
from service.runs.identify import parse_options
from service.settings import load_settings

TORQUES_NM = (1.0, 2.5, 4.0)
SPEED_RANGE_RPM = (1000, 2600)
UDC_V = 12.0
MAP_TORQUE_ROWS = 5  # issue 17's 5 x 5 map over 1..4 Nm: its refined map keeps these rows at least


def row_lut(speeds_rpm: list[float], thetas: list[complex], interpolation: str) -> Lut:
    """A one-row LUT (one torque, one U_dc) as the drive decodes it."""
    shape = (1, len(speeds_rpm), 1)
    return Lut(
        map_id=1,
        harmonic_order=6,
        torque_nm=np.array([1.0]),
        speed_rpm=np.array(speeds_rpm, dtype=float),
        udc_v=np.array([UDC_V]),
        theta_cos=np.array([z.real for z in thetas]).reshape(shape),
        theta_sin=np.array([z.imag for z in thetas]).reshape(shape),
        flags=np.full(shape, FLAG_OK, dtype=np.uint8),
        crc=0,
        interpolation=interpolation,
    )


def holds_between(speeds: list[float], thetas: list[complex], i: int, j: int, interpolation: str, target_db: float):
    """Every scanned speed strictly between breakpoints i and j holds target_db with cells at i and j only."""
    lut = row_lut([speeds[i], speeds[j]], [thetas[i], thetas[j]], interpolation)
    for k in range(i + 1, j):
        tc, ts = lut.theta(1.0, speeds[k], UDC_V)
        error = abs(complex(tc, ts) - thetas[k]) / abs(thetas[k])
        if error > 10.0 ** (-target_db / 20.0):
            return False
    return True


def fewest_breakpoints(
    speeds: list[float], thetas: list[complex], other_rows: list[list[complex]], interpolation: str, target_db: float
) -> list[float]:
    """The fewest breakpoints (scanned speeds) for which every row (thetas and other_rows, at `speeds`) holds."""
    chosen, i = [0], 0
    while i < len(speeds) - 1:
        j = i + 1
        while j + 1 < len(speeds) and all(
            holds_between(speeds, row, i, j + 1, interpolation, target_db) for row in [thetas, *other_rows]
        ):
            j += 1
        chosen.append(j)
        i = j
    return [speeds[k] for k in chosen]


def scan(svc, torque_nm: float, step_rpm: int) -> tuple[list[float], list[complex], int]:
    """theta* (probe, ok results only) every step_rpm; the count of points not ok."""
    speeds, thetas, not_ok = [], [], 0
    for n in range(SPEED_RANGE_RPM[0], SPEED_RANGE_RPM[1] + 1, step_rpm):
        op = OperatingPoint(torque_nm=torque_nm, speed_rpm=n, udc_v=UDC_V)
        try:
            job_id = svc.engine.submit_identification(op, "probe", parse_options("probe", {}))
        except EnvelopeError:  # beyond what the motor settings hold here (4 Nm past ~2450 rpm at 12 V): not ok
            not_ok += 1
            continue
        while (job := svc.storage.get_job(job_id))["state"] not in ("done", "failed", "cancelled"):
            time.sleep(0.02)
        result = svc.storage.get_result(job["result_id"]) if job.get("result_id") else None
        if result is None or result["status"] != "ok":
            not_ok += 1
            continue
        speeds.append(float(n))
        thetas.append(complex(result["theta_cos"], result["theta_sin"]))
    return speeds, thetas, not_ok


def one_truth(seed: int | None, step_rpm: int, target_db: float) -> None:
    name = "paper-bench" if seed is None else f"seed {seed}"
    overrides = {"server.db_path": str(Path(tempfile.mkdtemp()) / "density.db"), "emulator.speedup": 0}
    if seed is not None:
        overrides["emulator.seed"] = seed
    rows: dict[float, dict[float, complex]] = {}
    longest: dict[str, int] = {mode: 0 for mode in INTERPOLATIONS}
    with CalibrationService(load_settings(environ={}, overrides=overrides)) as svc:
        for torque_nm in TORQUES_NM:
            speeds, thetas, not_ok = scan(svc, torque_nm, step_rpm)
            rows[torque_nm] = dict(zip(speeds, thetas))
            turn = [
                abs(math.degrees(np.angle(b / a))) / (n1 - n0)
                for a, b, n0, n1 in zip(thetas, thetas[1:], speeds, speeds[1:])
            ]
            print(
                f"[{name}] {torque_nm:g} Nm: theta* every {step_rpm} rpm over {SPEED_RANGE_RPM[0]}..{SPEED_RANGE_RPM[1]} "
                f"rpm ({len(speeds)} ok, {not_ok} not ok), fastest turn {max(turn):.2f} deg/rpm",
                flush=True,
            )
            for mode in INTERPOLATIONS:
                points = fewest_breakpoints(speeds, thetas, [], mode, target_db)
                longest[mode] = max(longest[mode], len(points))
                print(f"   {mode:9s}: {len(points)} speed values for {target_db:g} dB: {[int(p) for p in points]}")
    # one speed axis for every row (a LUT is a full grid): the speeds scanned ok in every row
    common = sorted(set.intersection(*(set(r) for r in rows.values())))
    budget = int(2.5 * MAP_TORQUE_ROWS * 5)
    for mode in INTERPOLATIONS:
        first, *others = ([r[n] for n in common] for r in rows.values())
        shared = fewest_breakpoints(common, first, others, mode, target_db)
        print(
            f"[{name}] {mode}: one speed axis for the {len(rows)} rows needs {len(shared)} values, so a full-grid LUT "
            f"over {SPEED_RANGE_RPM[0]}..{SPEED_RANGE_RPM[1]} rpm has >= {len(shared)} x {MAP_TORQUE_ROWS} torque rows = "
            f"{len(shared) * MAP_TORQUE_ROWS} cells for {target_db:g} dB along speed alone (at the very least "
            f"{longest[mode]} x {MAP_TORQUE_ROWS} = {longest[mode] * MAP_TORQUE_ROWS}, the densest row's own); "
            f"2.5 x a 5 x 5 map: {budget}",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="None", help="comma-separated: None (paper-bench) and/or seed numbers")
    ap.add_argument("--step-rpm", type=int, default=10)
    ap.add_argument("--target-db", type=float, default=30.0)
    args = ap.parse_args()
    for text in args.seeds.split(","):
        one_truth(None if text.strip() == "None" else int(text), args.step_rpm, args.target_db)


if __name__ == "__main__":
    main()
