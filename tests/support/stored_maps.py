"""Maps stored as a finished sweep stores them (real SQLite, the service's own storage and map
building), for tests that need a map without running a sweep: exports, the download rules, the
dashboard. 2 x 2 x 1 grid; cell k (1..4, torque fastest) has gamma = k + gamma_offset_deg deg and
delta = 240 + 10 k deg; the cells in `failing` are stored as failed runs (not valid in a LUT)."""
from __future__ import annotations

import math

from service import __version__
from service.engine import SweepState
from service.harmonic import Phasor
from service.identification.adaptive import AdaptiveOptions
from service.identification.result import IdentificationResult
from service.maps import build_map_from_sweep
from service.operating_point import OperatingPoint
from service.public import result_row
from service.storage import Storage, now_iso

GRID = {"torque_nm": [1.0, 2.5], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]}
CELLS = [(t, n) for n in GRID["speed_rpm"] for t in GRID["torque_nm"]]      # in map order


def ok_result(gamma_deg: float, delta_deg: float) -> IdentificationResult:
    tc = math.radians(gamma_deg) * math.cos(math.radians(delta_deg))
    ts = -math.radians(gamma_deg) * math.sin(math.radians(delta_deg))
    return IdentificationResult("adaptive", 6, "ok", tc, ts, Phasor(1e-4, 0, 100, 6), Phasor(0.07, 0.01, 100, 6), 0.5, 8)


def sweep_with_results(storage: Storage, failing=(), gamma_offset_deg: float = 0.0) -> int:
    """A done sweep over GRID with one result per cell; `failing`: {(torque_nm, speed_rpm)} stored failed."""
    sweep_id = storage.create_sweep("adaptive", 6, GRID, {}, len(CELLS), "test-bench", __version__)
    for k, (t, n) in enumerate(CELLS, start=1):
        op = OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=12.0)
        if (t, n) in failing:
            row = result_row(op, "adaptive", AdaptiveOptions(), "test-bench", "t0", error="MeasurementError: boom",
                             sweep_id=sweep_id)
        else:
            row = result_row(op, "adaptive", AdaptiveOptions(), "test-bench", "t0",
                             ok_result(k + gamma_offset_deg, 240 + 10 * k), sweep_id=sweep_id)
        storage.insert_result(row)
    return sweep_id


def stored_map(storage: Storage, failing=(), gamma_offset_deg: float = 0.0) -> int:
    """The id of a new map built from a new sweep_with_results, which then reads done (as the engine
    leaves a finished sweep: a running service shows it as any other)."""
    sweep_id = sweep_with_results(storage, failing, gamma_offset_deg)
    map_id = build_map_from_sweep(storage, sweep_id)
    storage.update_sweep(sweep_id, state=SweepState.DONE.value, started_at=now_iso(), finished_at=now_iso(), map_id=map_id)
    return map_id
