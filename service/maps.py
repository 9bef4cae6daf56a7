"""Maps: the compensation over an operating-point grid, assembled from stored results.

A map references one result per grid cell (the latest for that operating point in the sweep);
cells whose identification failed keep their status so exports can mark them invalid.
"""
from __future__ import annotations

import json

from service import __version__
from service.storage import Storage



def build_map_from_sweep(storage: Storage, sweep_id: int) -> int:
    sweep = storage.get_sweep(sweep_id)
    if sweep is None:
        raise KeyError(f"sweep {sweep_id} does not exist")
    grid = json.loads(sweep["grid_json"])
    latest: dict[tuple[float, float, float], int] = {}
    for row in storage.sweep_results(sweep_id):
        latest[(row["torque_nm"], row["speed_rpm"], row["udc_v"])] = row["id"]
    cells = [(latest.get((t, n, u)), t, n, u)
             for u in grid["udc_v"] for n in grid["speed_rpm"] for t in grid["torque_nm"]]
    axes = {"torque_nm": grid["torque_nm"], "speed_rpm": grid["speed_rpm"], "udc_v": grid["udc_v"]}
    return storage.create_map(sweep_id, sweep["harmonic_order"], sweep["method"], axes, cells,
                              sweep["bench_identity"], __version__)
