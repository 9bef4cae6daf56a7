"""Maps built in storage from stored results with chosen thetas (no bench): a sweep, one result per
grid point (through result_row, as the engine stores them) and the map the engine would build."""

from __future__ import annotations

import math
from typing import Callable

from service import __version__
from service.identification.adaptive import AdaptiveOptions
from service.identification.result import IdentificationResult
from service.maps.build import build_map_from_sweep
from service.maps.view import MapCell, MapView
from service.model.harmonic import Phasor
from service.model.operating_point import OperatingPoint
from service.store.result_rows import result_row
from service.store.storage import Storage, now_iso

Point = tuple[float, float, float]

RESIDUAL = (2e-4, -1e-4)  # [a_c, a_s] left at the cell's own theta, full scale
UNCOMPENSATED = (0.06, 0.03)  # [a_c, a_s] with theta = 0, full scale
S_MEASURED = complex(0.8, -0.6)  # full scale per rad


def theta_of(gamma_deg: float, delta_deg: float) -> tuple[float, float]:
    """theta (rad) of gamma, delta (eq. 21-22: theta_cos = gamma cos delta, theta_sin = -gamma sin delta)."""
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return g * math.cos(d), -g * math.sin(d)


def store_sweep(
    storage: Storage,
    grid: dict[str, list[float]],
    theta: Callable[[Point], tuple[float, float]],
    status: dict[Point, str] | None = None,
    s_measured: complex | None = S_MEASURED,
    harmonic_order: int = 6,
    residual: tuple[float, float] = RESIDUAL,
    uncompensated: tuple[float, float] = UNCOMPENSATED,
) -> int:
    """A sweep over `grid` with one stored result per point, as the engine stores them: ok cells carry
    theta(point) (rad); `status` names the cells that are not ok ("failed" stores an error row
    without theta). Returns the sweep id (the sweep is not marked done)."""
    status = status or {}
    points = [(t, n, u) for u in grid["udc_v"] for n in grid["speed_rpm"] for t in grid["torque_nm"]]
    sweep_id = storage.create_sweep("adaptive", harmonic_order, grid, {}, len(points), "test-bench", __version__)
    for p in points:
        op = OperatingPoint(torque_nm=p[0], speed_rpm=p[1], udc_v=p[2])
        state = status.get(p, "ok")
        if state == "failed":
            row = result_row(
                op,
                "adaptive",
                AdaptiveOptions(),
                "test-bench",
                "t0",
                error="MeasurementError: boom",
                sweep_id=sweep_id,
                harmonic_order=harmonic_order,
            )
        else:
            tc, ts = theta(p)
            result = IdentificationResult(
                "adaptive",
                harmonic_order,
                state,
                tc,
                ts,
                Phasor(*residual, 1600, 6),
                Phasor(*uncompensated, 1600, 6),
                0.5,
                8,
                s_measured=s_measured,
                message="" if state == "ok" else "residual at the noise floor",
            )
            row = result_row(
                op,
                "adaptive",
                AdaptiveOptions(),
                "test-bench",
                "t0",
                result,
                sweep_id=sweep_id,
                harmonic_order=harmonic_order,
            )
        storage.insert_result(row)
    return sweep_id


def make_map(
    storage: Storage,
    grid: dict[str, list[float]],
    theta: Callable[[Point], tuple[float, float]],
    status: dict[Point, str] | None = None,
    s_measured: complex | None = S_MEASURED,
    harmonic_order: int = 6,
) -> int:
    """The map of a finished store_sweep (the sweep reads done, as the engine leaves it)."""
    sweep_id = store_sweep(storage, grid, theta, status, s_measured, harmonic_order)
    map_id = build_map_from_sweep(storage, sweep_id)
    storage.update_sweep(sweep_id, state="done", started_at=now_iso(), finished_at=now_iso(), map_id=map_id)
    return map_id


def map_dict(
    map_id: int, axes: dict[str, list[float]], cells: list[MapCell], status_counts: dict[str, int], **fields
) -> dict:
    """A map as GET /maps/{id} gives it (MapView.model_dump(), no validation), built from its cells without
    storage: harmonic order 6, adaptive, bench "test-bench" unless `fields` say otherwise (e.g. method, orders,
    further_orders)."""
    return MapView(
        **{
            "id": map_id,
            "sweep_id": 3,
            "harmonic_order": 6,
            "method": "adaptive",
            "bench_identity": "test-bench",
            "software_version": "0",
            "created_at": "2026-01-01T00:00:00Z",
            "axes": axes,
            "status_counts": status_counts,
            "cells": cells,
            **fields,
        }
    ).model_dump()
