"""The paper's warning in numbers (sec. 2.4, eq. 5-6; issue 28): cancelling order h by voltage-angle injection
raises order 2h by the gamma^2 term. What a map that compensates only the 6th does to the 12th.

Run: python -m tests.benchmarks.bench_second_harmonic [--seeds None,3,5] [--timing-only]

For each scenario (paper-bench with its 12th of its own, and seeded truths): a probe sweep over the issue's
10 x 10 map (torque 0.5..5 Nm x speed 500..3200 rpm at 12 V). Every result carries `order_2h` (the 12th
before and after, from the reference's and the final window's order spectra, and the window's noise). Printed:
cells whose 6th met 40 dB; over those, the 12th's change in dB (median, p90, max), the cells where it rose by
more than 3 dB / 10 dB while standing over 5 times the noise, and the 12th's median level against the 6th's
uncompensated level before and after (what a second order's compensation must take away).

Then, at speedup 1 (a real bench's clock), what cancelling the 6th and the 12th together costs against the 6th
alone: at three points of paper-bench, `probe` and `probe-orders` (orders [6, 12]) each in a run of its own;
printed per point and method: bench time (wall s from the move to the end of the measurement, the run's
make_safe after it not counted), plant time, the orders' suppression; and the ratio of the means.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from service.calibration_service import CalibrationService
from service.model.operating_point import OperatingPoint
from service.runs.identify import identify_at, parse_options
from service.settings import load_settings
from tests.benchmarks.bench_sweep_quality import run_sweep, sweep_service


def second_harmonic_figures(rows: list) -> dict:
    reached = [r for r in rows if (r["suppression_db"] or -1e9) >= 40.0]
    cells = []
    for r in reached:
        o2 = ((r["detail"] or {}).get("details") or {}).get("order_2h")
        if not o2:
            continue
        uncompensated_6 = float(np.hypot(r["uncompensated_a_c"], r["uncompensated_a_s"]))
        cells.append((o2, uncompensated_6))
    rise = np.array([o2["rise_db"] for o2, _ in cells])
    above = np.array([o2["compensated_fs"] > 5 * o2["noise_fs"] for o2, _ in cells])
    before_rel = np.array([20 * np.log10(o2["uncompensated_fs"] / u6) for o2, u6 in cells])
    after_rel = np.array([20 * np.log10(o2["compensated_fs"] / u6) for o2, u6 in cells])
    return {
        "n": len(rows),
        "reached": len(reached),
        "with_2h": len(cells),
        "median": float(np.median(rise)) if len(rise) else float("nan"),
        "p90": float(np.percentile(rise, 90)) if len(rise) else float("nan"),
        "max": float(np.max(rise)) if len(rise) else float("nan"),
        "rose_3db": int(np.sum((rise > 3.0) & above)),
        "rose_10db": int(np.sum((rise > 10.0) & above)),
        "before_rel": float(np.median(before_rel)) if len(cells) else float("nan"),
        "after_rel": float(np.median(after_rel)) if len(cells) else float("nan"),
    }


TIMING_POINTS = ((2.5, 2000.0), (1.0, 1000.0), (3.5, 1500.0))  # Nm, rpm at 12 V
METHODS = (("probe", {}), ("probe-orders", {"orders": [6, 12]}))


def two_orders_timing() -> None:
    db = Path(tempfile.mkdtemp()) / "timing.db"
    settings = load_settings(environ={}, overrides={"emulator.speedup": 1.0, "server.db_path": str(db)})
    means: dict[str, list[float]] = {m: [] for m, _ in METHODS}
    print(f"{'point':18s} {'method':13s} {'bench s':>8s} {'plant s':>8s}  orders")
    with CalibrationService(settings) as svc:
        for torque_nm, speed_rpm in TIMING_POINTS:
            op = OperatingPoint(torque_nm=torque_nm, speed_rpm=speed_rpm, udc_v=12)
            for method, options in METHODS:
                r = identify_at(svc.bench, settings, op, method, parse_options(method, options))
                bench_s = sum(r.details["bench_time_s"].values())
                means[method].append(bench_s)
                orders = r.details.get("orders") or [
                    {"order": 6, "status": r.status, "suppression_db": r.suppression_db}
                ]
                said = ", ".join(f"{o['order']}: {o['status']} {o['suppression_db']:.1f} dB" for o in orders)
                print(
                    f"{torque_nm:g} Nm {speed_rpm:g} rpm".ljust(18)
                    + f" {method:13s} {bench_s:>8.2f} {r.plant_time_s:>8.2f}  {said}",
                    flush=True,
                )
    one, two = (float(np.mean(means[m])) for m, _ in METHODS)
    print(f"bench time per point at speedup 1: one order {one:.2f} s, two orders {two:.2f} s, ratio {two / one:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="None,3,5")
    parser.add_argument("--timing-only", action="store_true", help="only the speedup-1 cost of two orders")
    args = parser.parse_args()
    two_orders_timing()
    if args.timing_only:
        return
    seeds = [None if s == "None" else int(s) for s in args.seeds.split(",")]
    print(
        f"{'scenario':20s} {'6th>=40dB':>9s} {'12th rise dB: median':>21s} {'p90':>6s} {'max':>6s} "
        f"{'>3dB':>5s} {'>10dB':>6s} {'12th/6th before':>16s} {'after':>6s}"
    )
    for seed in seeds:
        with sweep_service(seed, "second_harmonic.db") as svc:
            sweep = run_sweep(svc, "probe", decoupling=False)
        f = second_harmonic_figures(sweep["rows"])
        name = "paper-bench" if seed is None else f"paper-bench seed {seed}"
        print(
            f"{name:20s} {f['reached']:>5d}/{f['n']:<3d} {f['median']:>21.1f} {f['p90']:>6.1f} {f['max']:>6.1f} "
            f"{f['rose_3db']:>5d} {f['rose_10db']:>6d} {f['before_rel']:>16.1f} {f['after_rel']:>6.1f}"
            f"   (sweep wall {sweep['wall']:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
