"""The LUT in the drive (issue 17): sweep -> validation -> refinement -> validation, with cells, figures and
bench seconds (run: python -m tests.benchmarks.bench_refinement [--speedup 1] [--seeds None] [--map10]).

For each truth (paper-bench, and seeds given): a 5 x 5 probe sweep over 1..4 Nm x 1000..2600 rpm at 12 V
(it crosses the field-weakening onset), its map validated in the drive's own LUT mode (grid points and
midpoints), then refined with target 30 dB and a budget of 1.5 x its cells (the refined map at most 2.5 x
the cells), and the refined map's final validation. Printed: points >= 30 dB, medians, the worst, the
cells, the rounds, and the wall seconds of each step. With --map10: the grid points of a 10 x 10 probe map
(0.5..5 Nm x 500..3200 rpm) in LUT mode (median, share >= 40 dB; issue 17's figure for cells identified to
their margin). Speedup 1 (default) is what a bench pays; 0 runs as fast as the DAQ is read (same figures).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from service.api.public.jobs import job_public
from service.api.public.maps import map_public
from service.calibration_service import CalibrationService
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.runs.refinement import RefineRequest
from service.runs.validation import ValidationOptions
from service.settings import load_settings

GRID5 = Grid(torque_nm=[1.0, 1.75, 2.5, 3.25, 4.0], speed_rpm=[1000, 1400, 1800, 2200, 2600], udc_v=[12])
GRID10 = Grid(torque_nm=[0.5 * k for k in range(1, 11)], speed_rpm=[500 + 300 * k for k in range(10)], udc_v=[12])


def wait_job(svc, job_id: int) -> dict:
    while (job := svc.storage.get_job(job_id))["state"] not in ("done", "failed", "cancelled"):
        time.sleep(0.1)
    return job


def sweep(svc, grid: Grid) -> tuple[int, float]:
    t0 = time.perf_counter()
    sweep_id = svc.engine.submit_sweep(grid, "probe", parse_options("probe", {}))
    while svc.storage.get_sweep(sweep_id)["state"] in ("queued", "running"):
        time.sleep(0.1)
    return svc.storage.get_sweep(sweep_id)["map_id"], time.perf_counter() - t0


def validate(svc, map_id: int) -> tuple[list[dict], float]:
    t0 = time.perf_counter()
    job = wait_job(svc, svc.engine.submit("validation", map_id, True, ValidationOptions()))
    return svc.storage.validation_of_job(job["id"])["cells"], time.perf_counter() - t0


def figures(cells: list[dict], target_db: float = 30.0) -> str:
    values = [c["suppression_db"] for c in cells if c["status"] == "measured"]
    held = sum(v >= target_db for v in values)
    grid = [c["suppression_db"] for c in cells if c["status"] == "measured" and c["kind"] == "grid"]
    mid = [c["suppression_db"] for c in cells if c["status"] == "measured" and c["kind"] == "midpoint"]
    at_filled = [c["suppression_db"] for c in cells if c.get("map_cell_filled") and c["status"] == "measured"]
    worst = min(cells, key=lambda c: c["suppression_db"] if c["status"] == "measured" else 1e9)
    op = worst["operating_point"]
    return (
        f"{held}/{len(cells)} points >= {target_db:g} dB ({100 * held / max(len(cells), 1):.0f} %), median "
        f"{statistics.median(values):.1f} dB (grid {statistics.median(grid):.1f}, midpoints "
        f"{statistics.median(mid):.1f}), worst {worst['suppression_db']:.1f} dB at {op['torque_nm']:g} Nm / "
        f"{op['speed_rpm']:g} rpm ({worst['kind']}); filled cells: "
        + (", ".join(f"{v:.1f}" for v in at_filled) + " dB" if at_filled else "none")
    )


def one_truth(seed: int | None, speedup: float, map10: bool) -> None:
    db = Path(tempfile.mkdtemp()) / "refine.db"
    overrides = {"server.db_path": str(db), "emulator.speedup": speedup}
    if seed is not None:
        overrides["emulator.seed"] = seed
    with CalibrationService(load_settings(environ={}, overrides=overrides)) as svc:
        name = "paper-bench" if seed is None else f"seed {seed}"
        map_id, wall = sweep(svc, GRID5)
        m = map_public(svc.storage, map_id)
        print(f"[{name}] 5 x 5 sweep: {wall:.1f} s, {m.status_counts}, {m.filled_cells} filled", flush=True)
        cells, wall = validate(svc, map_id)
        print(f"[{name}] validation of map {map_id}: {wall:.1f} s, {figures(cells)}", flush=True)
        t0 = time.perf_counter()
        job = wait_job(svc, svc.engine.submit("refinement", map_id, RefineRequest(target_db=30, max_cells=37)))
        wall = time.perf_counter() - t0
        r = job_public(svc.storage, job).result
        final = map_public(svc.storage, r.map_id)
        print(
            f"[{name}] refinement: {wall:.1f} s, {len(r.rounds)} round(s), {r.cells_added} cells added, refined map "
            f"{r.map_id}: {len(final.cells)} cells ({len(final.cells) / len(m.cells):.2f} x), axes speed "
            f"{final.axes['speed_rpm']}, torque {final.axes['torque_nm']}; "
            + ("every point holds" if r.holds else f"stopped: {(r.stopped or '')[:160]}"),
            flush=True,
        )
        for rnd in r.rounds:
            print(
                f"   round {rnd.round}: map {rnd.map_id}, {rnd.points - rnd.below_target}/{rnd.points} >= 30 dB, "
                f"medians grid {rnd.grid_median_db:.1f} / midpoints {rnd.midpoint_median_db:.1f} dB, then inserted "
                f"{rnd.inserted or '-'}, re-measured {rnd.remeasured}",
                flush=True,
            )
        cells = svc.storage.latest_validation(r.map_id)["cells"]
        print(f"[{name}] final validation of map {r.map_id}: {figures(cells)}", flush=True)
        if map10:
            map_id, wall = sweep(svc, GRID10)
            cells, vwall = validate(svc, map_id)
            grid = [c["suppression_db"] for c in cells if c["kind"] == "grid" and c["status"] == "measured"]
            print(
                f"[{name}] 10 x 10 map {map_id} ({wall:.1f} s), its grid points in LUT mode ({vwall:.1f} s): median "
                f"{statistics.median(grid):.1f} dB, {sum(v >= 40 for v in grid)}/{len(grid)} >= 40 dB, min "
                f"{min(grid):.1f} dB",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--seeds", default="None", help="comma-separated: None (paper-bench) and/or seed numbers")
    ap.add_argument("--map10", action="store_true", help="also the grid points of a 10 x 10 map in LUT mode")
    args = ap.parse_args()
    for text in args.seeds.split(","):
        one_truth(None if text.strip() == "None" else int(text), args.speedup, args.map10)


if __name__ == "__main__":
    main()
