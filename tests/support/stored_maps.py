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
