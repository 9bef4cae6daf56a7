"""Map quality read time (run: python -m tests.benchmarks.bench_map_quality).

service.maps.quality.assess runs on every GET /maps/{id} and export: wall time per call on one core
for square maps linear in the operating point with a little noise and k planted outliers (each
flagged one by one, every statistic computed again after each), best of 5.
"""

from __future__ import annotations

import time

import numpy as np

from service.maps import quality as map_quality


def _map(n: int, outliers: int, rng: np.random.Generator) -> tuple[list[dict], dict]:
    axes = {
        "torque_nm": [float(i) for i in range(n)],
        "speed_rpm": [1000.0 + 100.0 * i for i in range(n)],
        "udc_v": [12.0],
    }
    cells = [
        {
            "torque_nm": t,
            "speed_rpm": s,
            "udc_v": 12.0,
            "status": "ok",
            "theta_cos": 0.05 + 1e-3 * t + 1e-5 * s + float(rng.normal(0, 2e-5)),
            "theta_sin": -0.02 + 5e-4 * t,
        }
        for t in axes["torque_nm"]
        for s in axes["speed_rpm"]
    ]
    for i in rng.choice(len(cells), outliers, replace=False):
        cells[i]["theta_cos"] += 0.05
    return cells, axes


def main() -> None:
    rng = np.random.default_rng(1)
    print(f"{'cells':>6} {'planted':>8} {'flagged':>8} {'ms per assess':>14}")
    for n, k in ((3, 1), (10, 0), (10, 5), (20, 10), (32, 40)):
        cells, axes = _map(n, k, rng)
        best = float("inf")
        for _ in range(5):
            t0 = time.perf_counter()
            q = map_quality.assess(cells, axes)
            best = min(best, time.perf_counter() - t0)
        print(f"{n * n:>6} {k:>8} {q.count('outlier'):>8} {best * 1e3:>14.1f}")


if __name__ == "__main__":
    main()
