"""Maps stored as a finished sweep stores them (real SQLite, the service's own storage and map
building), for tests that need a map without running a sweep: exports, the download rules, the
dashboard. 2 x 2 x 1 grid; cell k (1..4, torque fastest) has gamma = k + gamma_offset_deg deg and
delta = 240 + 10 k deg; the cells in `failing` are stored as failed runs (not valid in a LUT)."""

from __future__ import annotations

from service.store.storage import Storage
from tests.support.maps import make_map, store_sweep, theta_of

GRID = {"torque_nm": [1.0, 2.5], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]}
CELLS = [(t, n) for n in GRID["speed_rpm"] for t in GRID["torque_nm"]]  # in map order


def _theta(gamma_offset_deg: float):
    def theta(p):
        k = CELLS.index((p[0], p[1])) + 1
        return theta_of(k + gamma_offset_deg, 240 + 10 * k)

    return theta


def _failing(failing) -> dict:
    return {(t, n, 12.0): "failed" for t, n in failing}


def sweep_with_results(storage: Storage, failing=(), gamma_offset_deg: float = 0.0) -> int:
    """A sweep over GRID with one result per cell; `failing`: {(torque_nm, speed_rpm)} stored failed."""
    return store_sweep(
        storage,
        GRID,
        _theta(gamma_offset_deg),
        _failing(failing),
        s_measured=None,
        residual=(1e-4, 0.0),
        uncompensated=(0.07, 0.01),
    )


def stored_map(storage: Storage, failing=(), gamma_offset_deg: float = 0.0) -> int:
    """The id of a new map of a finished sweep over GRID (a running service shows it as any other)."""
    return make_map(storage, GRID, _theta(gamma_offset_deg), _failing(failing), s_measured=None)


def stored_two_order_map(storage: Storage) -> int:
    """A map of orders 6 and 12 over GRID: the 6th as stored_map's; the 12th's cell k has gamma = k / 2 deg and
    delta = 30 k deg, ok but for cell 4 (below target, its theta kept as a fill)."""
    sweep_id = sweep_with_results(storage)
    rows = {(r["torque_nm"], r["speed_rpm"]): r for r in storage.sweep_results(sweep_id)}
    twelfth = []
    for k, (t, n) in enumerate(CELLS, start=1):
        c, s = theta_of(k / 2, 30 * k)
        ok = k < 4
        twelfth.append(
            {
                "status": "ok" if ok else "below_target",
                "theta_cos": c,
                "theta_sin": s,
                "suppression_db": 45.0 if ok else 31.0,
                "target_db": 40.0,
                "error": None if ok else "31.0 dB, below the 40 dB target",
                **({} if ok else {"fill_theta_cos": c, "fill_theta_sin": s, "fill_source": "measured: its own theta"}),
            }
        )
    return storage.create_map(
        sweep_id,
        6,
        "probe-orders",
        GRID,
        [(rows[(t, n)]["id"], t, n, 12.0) for t, n in CELLS],
        "test-bench",
        "0",
        further_orders=[{"order": 12, "cells": twelfth}],
    )
