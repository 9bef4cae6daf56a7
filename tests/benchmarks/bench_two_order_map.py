"""A map of two orders (issue 28): the 6th and the 12th compensated jointly over a 10 x 10 map, its LUT of both orders
validated in the drive's LUT mode at the grid points and midpoints and along run-ups, each order on its own.

Run: python -m tests.benchmarks.bench_two_order_map [--seeds None,3,5,7] [--validate-seeds None] [--timing-grid 10x10|5x5]

For each scenario (paper-bench with its own 12th, and seeded machines): a sweep of method probe-orders, orders
[6, 12], over torque 0.5..5 Nm x speed 500..3200 rpm at 12 V (drive decoupling on: the nominal current loop
counteracts at 500 rpm) at speedup 0. Printed per order: cells ok, cells >= 40 dB, of the reachable cells (those
the envelope lets run; the others are `not run`, never counted as a figure), and the stored results that claim ok
below their target (must be 0), and the cells where an order ends below 0 dB while it stands >= 20 dB above the
final window's noise (worse than no compensation). The cells not ok are classed by their reason; those whose 12th
the method judged not confirmable (its 40 dB within 3 sigma of the noise of the longest window) are counted apart.
For the scenarios of --validate-seeds: the map's LUT of both orders (format version 8) downloaded with its fills and
validated in the drive's LUT mode (every grid point and midpoint, target 30 dB): per order points, held, median and
minimum; then run-ups 1000 -> 2600 rpm at 100 rpm/s at 1.5 and 3 Nm without and with the LUT: per order the
median and the worst suppression over the speed bins where the order stands >= 20 dB above the bin's noise
floor without the LUT (the order cuts before and after).
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path

from service.calibration_service import CalibrationService
from service.identification.orders import NOT_CONFIRMABLE
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.runs.runup import RunupRequest, runup_in_run
from service.runs.validation import ValidationOptions
from service.settings import load_settings
from tests.benchmarks.bench_sweep_quality import SPEEDS, TORQUES

ORDERS = [6, 12]
REASONS = ("noise floor", "not confirmed", "gamma_max", "stopped falling", "shaft resonance", "over-range")


def _service(seed: int | None, directory: Path, speedup: float = 0.0) -> CalibrationService:
    settings = load_settings(
        environ={},
        overrides={"emulator.speedup": speedup, "server.db_path": str(directory / "two.db"), "emulator.seed": seed},
    )
    return CalibrationService(settings)


def _wait(svc: CalibrationService, done, what: str, timeout_s: float = 3600.0):
    deadline = time.monotonic() + timeout_s
    while (value := done()) is None:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} did not finish in {timeout_s:.0f} s")
        time.sleep(0.5)
    return value


def sweep_orders(svc: CalibrationService, method: str = "probe-orders", grid: Grid | None = None) -> tuple[int, dict]:
    """The 10 x 10 sweep with `method` (probe: the 6th alone, for comparison) and its figures per order."""
    extra = {"orders": ORDERS} if method == "probe-orders" else {}
    options = parse_options(method, {**extra, "decoupling": True})
    grid = grid or Grid(torque_nm=TORQUES, speed_rpm=SPEEDS, udc_v=[12])
    sweep_id = svc.engine.submit_sweep(grid, method, options)

    def finished():
        sweep = svc.storage.get_sweep(sweep_id)
        return sweep if sweep["state"] in ("done", "failed", "cancelled") else None

    sweep = _wait(svc, finished, "the sweep")
    rows = svc.storage.sweep_results(sweep_id)
    reachable = [r for r in rows if not (r["error"] or "").startswith("not run")]
    figures: dict = {
        "reachable": len(reachable),
        "cells": len(rows),
        "state": sweep["state"],
        "plant_s": [r["plant_time_s"] for r in reachable],
        "wall_s": _seconds(sweep["started_at"], sweep["finished_at"]),
    }
    for h in ORDERS:
        ok = ge40 = dishonest = resolvable = resolvable_ok = unconfirmable = harmed = 0
        reasons: Counter = Counter()
        for r in reachable:
            o = next((o for o in (r["detail"].get("details") or {}).get("orders") or [] if o["order"] == h), None)
            if o is None and h == r["harmonic_order"]:  # a result of one order: its own fields
                o = {**r, "reason": r["error"]}
            if o is None:
                reasons[f"{r['status']}: no figure of the order"] += 1
                continue
            ok += o["status"] == "ok"
            # resolvable: the order stands >= target + 10 dB above the final window's noise (else 40 dB cannot be
            # confirmed at the longest window: the sensor's noise, not the method, decides there)
            floor = o.get("noise_floor_db")
            if floor is not None and -floor >= (o.get("target_db") or 40.0) + 10.0:
                resolvable += 1
                resolvable_ok += o["status"] == "ok"
            # the method's own judgement from its reference: 40 dB within the noise of the longest window
            unconfirmable += NOT_CONFIRMABLE in (o["reason"] or "")
            # worse than no compensation where the order stands >= 20 dB above the final window's noise
            harmed += floor is not None and floor <= -20.0 and (o["suppression_db"] or 0.0) < 0.0
            ge40 += (o["suppression_db"] or -1e9) >= 40.0
            dishonest += o["status"] == "ok" and (o["suppression_db"] or -1e9) < o["target_db"]
            if o["status"] != "ok":
                reason = next((p for p in REASONS if p in (o["reason"] or "")), (o["reason"] or "")[:50])
                reasons[f"{o['status']}: {reason}"] += 1
        figures[h] = {
            "ok": ok,
            "ge40": ge40,
            "dishonest": dishonest,
            "reasons": reasons,
            "resolvable": resolvable,
            "resolvable_ok": resolvable_ok,
            "unconfirmable": unconfirmable,
            "harmed": harmed,
        }
    return int(sweep["map_id"]), figures


def _seconds(started_at: str, finished_at: str) -> float:
    from datetime import datetime

    return (datetime.fromisoformat(finished_at) - datetime.fromisoformat(started_at)).total_seconds()


# the bench-time comparison at a real bench's clock (speedup 1), one order against two: a 5 x 5 map, or the 10 x 10
# map of the figures (--timing-grid 10x10)
TIMING_GRIDS = {
    "5x5": Grid(torque_nm=[1.0, 1.75, 2.5, 3.25, 4.0], speed_rpm=[800, 1250, 1700, 2150, 2600], udc_v=[12]),
    "10x10": Grid(torque_nm=TORQUES, speed_rpm=SPEEDS, udc_v=[12]),
}


# Two windows at least: the one a last step is taken from and the one that confirms. With white sensor noise a
# window's sigma^2 ~ 1/T; a step from a window of sigma_1 lands at a residual of about sqrt(2) sigma_1, and the
# confirmation needs that residual + 2 sigma_2 <= L (common.meets). The least T_1 + T_2 under that constraint, found
# numerically below, is at sigma_1 ~ 0.31 L, sigma_2 ~ 0.28 L: T_1 + T_2 = (10.2 + 12.9) / L^2 in units of a window
# of sigma 1, the smallest confirmable L of the point deciding.
def _least_two_windows() -> float:
    best = math.inf
    for i in range(1, 700):
        sigma_1 = i / 1000.0  # in units of L
        sigma_2 = (1.0 - math.sqrt(2.0) * sigma_1) / 2.0
        if sigma_2 > 0:
            best = min(best, 1.0 / sigma_1**2 + 1.0 / sigma_2**2)
    return best


LEAST_TWO_WINDOWS = _least_two_windows()


def ideal_plant_s(row: dict, target_db: float = 40.0) -> float | None:
    """The plant seconds an ideal method of two windows needs at this point of a probe-orders sweep: each order's
    noise taken from its final window (its own noise_floor_db: sqrt(2) sigma against its uncompensated amplitude,
    sigma over the window's duration, from the orders' history: end time minus the one before minus the settle),
    and the order among those not said 'not confirmable here' whose target L needs the longest window deciding."""
    orders = (row["detail"].get("details") or {}).get("orders") or []
    history = (row.get("traces") or {}).get("orders_history") or []
    if len(history) < 2 or not orders:
        return None
    settle_s = float((row.get("options") or {}).get("settle_s", 0.005))
    final_s = history[-1][0] - history[-2][0] - settle_s
    needs = []
    for o in orders:
        if NOT_CONFIRMABLE in (o["reason"] or "") or o.get("noise_floor_db") is None:
            continue
        level_fs = o["uncompensated"]["amplitude"] * 10.0 ** (-target_db / 20.0)
        sigma_fs = o["uncompensated"]["amplitude"] * 10.0 ** (o["noise_floor_db"] / 20.0) / math.sqrt(2.0)
        needs.append(sigma_fs**2 / level_fs**2)
    if final_s <= 0 or not needs:
        return None
    return final_s * LEAST_TWO_WINDOWS * max(needs)


def reference_plant_s(row: dict) -> float | None:
    """The plant seconds of a probe-orders result's reference (its windows at theta = 0 before any injection, each
    order's uncompensated phasor), which every method of several orders needs before its first step."""
    history = (row.get("traces") or {}).get("orders_history") or []
    if not history:
        return None
    n_orders = (len(history[0]) - 1) // 3
    ends = [h[0] for h in history if not any(h[1 : 1 + 2 * n_orders])]
    return ends[-1] if ends and history[0] and not any(history[0][1 : 1 + 2 * n_orders]) else None


def timing(seed: int | None, grid_name: str = "10x10") -> None:
    """Bench seconds per point (the sweep's wall time over its points, moves included) of the 5 x 5 (or 10 x 10) map
    at speedup 1, the 6th alone (probe) against the 6th and 12th (probe-orders); and plant seconds per point. Then the
    floor the sensor's noise sets: an ideal method's plant time per point (its reference, reference_plant_s, and two
    windows, ideal_plant_s; never less than the single order's own at that point) with the single order's overhead
    per point (bench time less plant time), against the same single-order figure."""
    per_point, plant, overhead_s = {}, {}, 0.0
    for method in ("probe", "probe-orders"):
        with tempfile.TemporaryDirectory() as tmp, _service(seed, Path(tmp), speedup=1.0) as svc:
            _map_id, f = sweep_orders(svc, method, TIMING_GRIDS[grid_name])
            n = f["reachable"]
            per_point[method] = f["wall_s"] / n
            rows = [r for r in svc.storage.sweep_results(1) if not (r["error"] or "").startswith("not run")]
            plant[method] = {(r["torque_nm"], r["speed_rpm"]): r for r in rows}
            if method == "probe":
                overhead_s = per_point[method] - statistics.mean(f["plant_s"])
            print(
                f"  {method:12s} {grid_name} at speedup 1: {n} points run, {f['wall_s']:.0f} s bench time = "
                f"{per_point[method]:.2f} s a point; plant median {statistics.median(f['plant_s']):.2f} s, "
                f"mean {statistics.mean(f['plant_s']):.2f} s",
                flush=True,
            )
    print(
        f"  two orders / one order: {per_point['probe-orders'] / per_point['probe']:.2f} x bench time a point (target <= 1.6 x)"
    )
    ideal, ideal_no_reference = [], []
    for key, row in plant["probe-orders"].items():
        single = plant["probe"].get(key)
        floor_s, reference_s = ideal_plant_s(row), reference_plant_s(row)
        if single is not None and floor_s is not None and reference_s is not None:
            ideal.append(max(reference_s + floor_s, single["plant_time_s"]))
            ideal_no_reference.append(max(floor_s, single["plant_time_s"]))
    if ideal:
        floor_ratio = (overhead_s + statistics.mean(ideal)) / per_point["probe"]
        bare_ratio = (overhead_s + statistics.mean(ideal_no_reference)) / per_point["probe"]
        print(
            f"  the sensor's floor: an ideal method needs {statistics.mean(ideal):.2f} s plant a point, its reference "
            f"and two windows (mean over {len(ideal)} points); with the single order's {overhead_s:.2f} s of overhead "
            f"a point, {floor_ratio:.2f} x bench time at best ({bare_ratio:.2f} x were the reference free)"
        )


def validate(svc: CalibrationService, map_id: int) -> dict:
    job_id = svc.submit_validation(map_id, True, ValidationOptions())

    def finished():
        job = svc.storage.get_job(job_id)
        return job if job["state"] in ("done", "failed", "cancelled") else None

    job = _wait(svc, finished, "the validation")
    row = svc.storage.validation_of_job(job_id)
    return {"state": job["state"], "summary": row["summary"], "download": row["download"]}


def runup_cuts(svc: CalibrationService, torque_nm: float) -> dict[int, tuple[float, float, int]]:
    """Per order (median, worst, bins judged) suppression along the run-up pair at `torque_nm`."""
    cuts = {}
    for injection in ("off", "lut"):
        # every order of the survey fitted (orders None): an order left unfitted leaks into the others' cuts
        req = RunupRequest(
            torque_nm=torque_nm,
            udc_v=12,
            speed_rpm=(1000, 2600),
            rate_rpm_per_s=100,
            injection=injection,
            decoupling=True,
        )
        cuts[injection] = runup_in_run(svc.bench, svc.settings, req, None)
    off, lut = cuts["off"], cuts["lut"]
    out = {}
    for h in ORDERS:
        k, values = off["orders"].index(h), []
        for i, speed in enumerate(off["speed_rpm"]):
            if speed not in lut["speed_rpm"]:
                continue
            j = lut["speed_rpm"].index(speed)
            before, floor = off["amplitude"][k][i], off["noise_floor"][i]
            after = lut["amplitude"][lut["orders"].index(h)][j]
            if before <= 0 or after <= 0 or floor <= 0 or 20 * math.log10(before / floor) < 20.0:
                continue
            values.append(20 * math.log10(before / after))
        out[h] = (statistics.median(values), min(values), len(values)) if values else (math.nan, math.nan, 0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="None,3,5,7")
    parser.add_argument("--validate-seeds", default="None")
    parser.add_argument("--method", default="probe-orders", help="probe: the 6th alone (the LUT of one order)")
    parser.add_argument("--timing-seeds", default="None", help="scenarios of the bench-time comparison at speedup 1")
    parser.add_argument(
        "--timing-grid", default="10x10", choices=sorted(TIMING_GRIDS), help="its map (default: the issue's 10 x 10)"
    )
    args = parser.parse_args()
    seeds = [None if s == "None" else int(s) for s in args.seeds.split(",") if s]
    validate_seeds = {None if s == "None" else int(s) for s in args.validate_seeds.split(",") if s}
    for seed in [None if s == "None" else int(s) for s in args.timing_seeds.split(",") if s]:
        print(
            f"{'paper-bench' if seed is None else f'paper-bench seed {seed}'}: bench time per point, one order against two"
        )
        timing(seed, args.timing_grid)
    for seed in seeds:
        name = "paper-bench" if seed is None else f"paper-bench seed {seed}"
        with tempfile.TemporaryDirectory() as tmp, _service(seed, Path(tmp)) as svc:
            t0 = time.perf_counter()
            map_id, f = sweep_orders(svc, args.method)
            n = f["reachable"]
            print(
                f"{name}: 10 x 10 two-order sweep {f['state']} in {time.perf_counter() - t0:.0f} s wall, "
                f"{n} of {f['cells']} cells reachable (the others not run: outside the envelope)",
                flush=True,
            )
            for h in ORDERS:
                o = f[h]
                print(
                    f"  order {h:2d}: ok {o['ok']}/{n} ({100 * o['ok'] / n:.0f} %), >= 40 dB {o['ge40']}/{n} "
                    f"({100 * o['ge40'] / n:.0f} %), ok below target {o['dishonest']} (target 95 % ok), below 0 dB where "
                    f">= 20 dB above the noise {o['harmed']}"
                )
                if o["resolvable"]:
                    print(
                        f"      of the {o['resolvable']} cells where it stands >= 50 dB above the final window's noise: "
                        f"ok {o['resolvable_ok']} ({100 * o['resolvable_ok'] / o['resolvable']:.0f} %)"
                    )
                if o["unconfirmable"]:
                    confirmable = n - o["unconfirmable"]
                    print(
                        f"      {o['unconfirmable']} cells said 'not confirmable here' (its target within 3 sigma of the "
                        f"longest window's noise); of the other {confirmable}: ok {o['ok']} ({100 * o['ok'] / confirmable:.0f} %)"
                    )
                for reason, count in o["reasons"].most_common(4):
                    print(f"      {count:3d} x {reason}")
            if seed not in validate_seeds:
                continue
            v = validate(svc, map_id)
            print(
                f"  LUT of both orders (format version {v['download']['format_version']}, {v['download']['bytes']} "
                f"bytes) validated in LUT mode ({v['state']}, target 30 dB):"
            )
            for o in v["summary"].get("orders") or []:
                print(
                    f"    order {o['order']:2d}: {o['held']}/{o['points']} points hold, median {o['median_db']:.1f} dB, "
                    f"min {o['min_db']:.1f} dB"
                )
            for torque_nm in (1.5, 3.0):
                for h, (median, worst, bins) in runup_cuts(svc, torque_nm).items():
                    print(
                        f"    run-up 1000 -> 2600 rpm at {torque_nm:g} Nm, order {h:2d}: LUT against none median "
                        f"{median:.1f} dB, worst {worst:.1f} dB over {bins} bins >= 20 dB above the floor"
                    )


if __name__ == "__main__":
    main()
