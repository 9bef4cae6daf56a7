"""A LUT judged and refined along run-ups (issue 27), per machine: sweep -> validation -> refinement -> validation.

Run: python -m tests.benchmarks.bench_runup_refinement [--seeds -,3] [--max-cells 40] [--rate 100]
     [--interpolation cartesian|polar] [--lut-cells int11-sparse] [--floor-db 45] [--settle-s 0.005]
     [--dump DIR] [--cell-options JSON] [--max-bench-s 720]

On the emulated bench (speedup 0, or --speedup 1 for a real bench's clock; plant seconds on the DAQ clock, every
point's settling included, are what a bench pays but for each point's storage and commands, which --speedup 1's wall
adds): a 4 x 5 probe map over 1..4 Nm x 1000..2600 rpm at 12 V, validated as it is (grid, midpoints, run-ups at up
to --runup-torques torques),
then a refinement (POST /maps/{id}/refine: placement from curves, then the same validation), within max_cells and
max_bytes 2048 (int11 cells: 3 bytes a cell; --lut-cells int16 for 5, float32 for 9), in the drive's default
interpolation between cells unless --interpolation names one (placement, validation and the LUT alike). Printed
per round: the LUT's bytes and cells, the points judged (grid, midpoints, run-up bins) and how many hold at 30 dB,
median and minimum, the points where the LUT makes the order worse than no compensation (harmful) and the cells
given injection off by the guard, and the round's plant seconds (settling and measurements); then the totals, and
the points that still fail by kind (grid, midpoint, run-up bin): the share held depends on how many points the grid
has to judge.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import Counter
from pathlib import Path

from drivers.lut_image import DEFAULT_INTERPOLATION, INTERPOLATIONS
from service.calibration_service import CalibrationService
from service.maps.view import map_view
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.runs.refinement import RefineRequest
from service.runs.validation import ValidationOptions, judged_points
from service.settings import load_settings
from service.store.records import bench_plant_s
from tests.support.waiting import wait_run_finished

GRID = Grid(torque_nm=[1, 2, 3, 4], speed_rpm=[1000, 1400, 1800, 2200, 2600], udc_v=[12])
# the validations' LUT windows end 15 dB under the 30 dB target (the service's default, 55 dB, resolves figures far
# above the target), and 5 ms after an injection mode switch (the shaft mode is fitted in the window, service.model.
# demodulation): paper-bench's calibration from nothing then costs 797 s of bench time instead of 1128 s, holding the
# same points within 1 % (measured: the README)
FLOOR_DB = 45.0
SETTLE_S = 0.005
# the 15 min at a real bench's clock, as the refinement's budget in bench time (plant s on the DAQ clock, each
# point's settling counted): the wall adds each cell's storage and recording, each run-up's analysis and each round's
# map and LUT download, 1.15-1.16 x the plant time measured, and the sweep takes ~16 s: 720 s leaves a few % to spare
MAX_BENCH_S = 720.0
ROUND_KEYS = (
    "round",
    "bytes",
    "cells",
    "points_judged",
    "held",
    "median_db",
    "min_db",
    "harmful",
    "injection_off",
    "no_injection",
)


def machine(
    seed: int | None,
    max_cells: int,
    rate_rpm_per_s: float,
    placement: str,
    runup_torques: int,
    lut_cells: str,
    dump_dir: str | None = None,
    interpolation: str | None = None,
    floor_db: float = FLOOR_DB,
    settle_s: float = SETTLE_S,
    speedup: float = 0.0,
    cell_options: dict | None = None,
    max_bench_s: float | None = None,
) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        overrides: dict = {"emulator.speedup": speedup, "server.db_path": str(Path(tmp) / "r.db")}
        if seed is not None:
            overrides["emulator.seed"] = seed
        with CalibrationService(load_settings(environ={}, overrides=overrides)) as svc:
            svc.start(status_period_s=None)
            t0 = time.perf_counter()
            sweep_id = svc.engine.submit_sweep(GRID, "probe", parse_options("probe", {}))
            sweep = wait_run_finished(lambda: svc.storage.get_sweep(sweep_id), 3600.0, f"sweep {sweep_id}")
            sweep_wall_s = time.perf_counter() - t0
            sweep_plant_s = sum(bench_plant_s(r) for r in svc.storage.sweep_results(sweep_id))
            options = ValidationOptions(
                runups=True,
                runup_rate_rpm_per_s=rate_rpm_per_s,
                runup_torques_max=runup_torques,
                interpolation=interpolation,
                floor_db=floor_db,
                settle_s=settle_s,
            )
            # the sweep's map as it is, judged the same way (the "before"; not part of the calibration's bench time)
            job_id = svc.engine.submit("validation", sweep["map_id"], True, options)
            wait_run_finished(lambda: svc.storage.get_job(job_id), 3600.0, f"validation job {job_id}")
            before = (svc.storage.validation_of_job(job_id) or {}).get("summary") or {}
            print(
                f"machine {'paper-bench' if seed is None else f'seed {seed}'}: sweep {GRID.size()} cells, plant "
                f"{sweep_plant_s:.0f} s; its map validated: held {before.get('held')}/{before.get('points')}, median "
                f"{before.get('median_db') or float('nan'):.1f} dB, min {before.get('min_db') or float('nan'):.1f} dB"
            )
            request = RefineRequest(
                options=cell_options or {},
                target_db=30,
                max_cells=max_cells,
                max_bytes=2048,
                max_bench_s=max_bench_s,
                placement=placement,
                lut_cells=lut_cells,
                validation=options,
            )
            t1 = time.perf_counter()
            job_id = svc.engine.submit("refinement", sweep["map_id"], request)
            job = wait_run_finished(lambda: svc.storage.get_job(job_id), 7200.0, f"refinement job {job_id}")
            state = svc.storage.get_sweep(job["sweep_id"])["refinement"]
            print(
                f"machine {'paper-bench' if seed is None else f'seed {seed}'}: job {job['state']}, wall at speedup "
                f"{speedup:g}: sweep {sweep_wall_s:.0f} s + refinement {time.perf_counter() - t1:.0f} s (from nothing; "
                f"all {time.perf_counter() - t0:.0f} s with the sweep's map validated before)"
            )
            for r in state.get("placement_rounds", []):
                print(
                    f"  round {r['round']} placement: candidates {r['candidates']}, inserted "
                    f"{ {a: len(v) for a, v in r['inserted'].items()} }, worst predicted {r['worst_predicted_db']}, "
                    f"bytes {r['bytes']}, cells {r['cells']}, plant {r['plant_time_s']:.0f} s"
                )
            for r in state["rounds"]:
                figures = ", ".join(
                    f"{k} {r[k]:.1f}" if isinstance(r.get(k), float) else f"{k} {r.get(k)}" for k in ROUND_KEYS
                )
                print(f"  {figures}, plant {r.get('plant_time_s', 0.0):.0f} s")
            final_validation = svc.storage.latest_validation(state["current_map_id"])
            if dump_dir is not None:  # the final map and its validation, for a closer look
                view = map_view(svc.storage, state["current_map_id"])
                (Path(dump_dir) / f"{'paper-bench' if seed is None else f'seed-{seed}'}.json").write_text(
                    json.dumps(
                        {
                            "map": view.model_dump() if view else None,
                            "cells": (final_validation or {}).get("cells"),
                            "refinement": state,
                        },
                        default=str,
                    )
                )
            final = map_view(svc.storage, state["current_map_id"])
            outliers = sum(1 for c in final.cells if c.quality == "outlier") if final else None
            print(
                f"  refined map {state['current_map_id']}: {outliers} cell(s) called outliers; bench time sweep + "
                f"refinement {sweep_plant_s + state.get('plant_time_s', 0.0):.0f} plant s"
            )
            print(f"  total plant {state.get('plant_time_s', 0.0):.0f} s; stopped: {state['stopped']}")
            # the share held depends on how many points a grid has to judge (a denser grid has more midpoints away
            # from the turn): the points that fail, by kind, are the figure that compares calibrations
            judged = judged_points((final_validation or {}).get("cells") or [])
            failing = Counter(c["kind"] for c in judged if not c["holds"])
            print(
                f"  failing after refinement: {sum(failing.values())} of {len(judged)} judged points "
                f"({', '.join(f'{kind} {n}' for kind, n in sorted(failing.items())) or 'none'})"
            )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="-,3", help="comma-separated; - is paper-bench")
    parser.add_argument("--max-cells", type=int, default=1000)
    parser.add_argument("--runup-torques", type=int, default=7, help="run-ups at most at this many torques")
    parser.add_argument(
        "--rate", type=float, default=100.0, help="the validation's run-up rate, rpm/s (the service's default)"
    )
    parser.add_argument("--placement", default="curves", choices=("curves", "validation"))
    parser.add_argument("--dump", default=None, help="a directory: the final map and validation as JSON per machine")
    parser.add_argument(
        "--lut-cells",
        default="int11",
        choices=("int11", "int11-sparse", "int16", "float32"),
        help="the LUT's cell format",
    )
    parser.add_argument(
        "--interpolation",
        default=None,
        choices=list(INTERPOLATIONS),
        help=f"what the drive interpolates between cells (default {DEFAULT_INTERPOLATION})",
    )
    parser.add_argument(
        "--floor-db",
        type=float,
        default=FLOOR_DB,
        help=f"the validations' noise floor below the uncompensated order, dB (default {FLOOR_DB:g}; the service's 55)",
    )
    parser.add_argument(
        "--settle-s",
        type=float,
        default=SETTLE_S,
        help=f"the validations' plant time after an injection mode switch, s (default {SETTLE_S:g}; the service's 0.02)",
    )
    parser.add_argument("--speedup", type=float, default=0.0, help="the emulator's (1: a real bench's clock)")
    parser.add_argument(
        "--max-bench-s",
        type=float,
        default=MAX_BENCH_S,
        help=f"the refinement's bench time budget, plant s (default {MAX_BENCH_S:g}; 0: none)",
    )
    parser.add_argument(
        "--cell-options", default="{}", help='the new cells\' method options, JSON (e.g. {"stop_margin_db": 0})'
    )
    args = parser.parse_args()
    for text in args.seeds.split(","):
        machine(
            None if text == "-" else int(text),
            args.max_cells,
            args.rate,
            args.placement,
            args.runup_torques,
            args.lut_cells,
            args.dump,
            args.interpolation,
            args.floor_db,
            args.settle_s,
            args.speedup,
            json.loads(args.cell_options),
            args.max_bench_s or None,
        )


if __name__ == "__main__":
    main()
