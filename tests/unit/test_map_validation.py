"""Map validation (service/runs/validation.py): the finer grid, the summary, the refusals, migration 0006
keeping every job, and the summary in every export (closed forms and independent counts, real SQLite)."""

import json
import sqlite3
import statistics

import pytest

from service.api.public.jobs import job_public
from service.api.public.maps import map_public
from service.identification.adaptive import AdaptiveOptions
from service.maps.build import build_map_from_sweep
from service.maps.lut_export import export_map
from service.model.operating_point import OperatingPoint
from service.runs.plans import settling_order
from service.runs.validation import (
    ValidationRefused,
    ValidationRun,
    check_validatable,
    finer_axis,
    store_validation,
    summarize,
    validation_points,
)
from service.store.migrations import migration_files
from service.store.result_rows import result_row
from service.store.storage import MIGRATIONS_DIR, Storage
from service.store.storage.rows import encode_columns
from tests.support.operating_points import OP1_POINT
from tests.support.stored_maps import sweep_with_results


def test_finer_axis_holds_the_grid_values_and_their_midpoints():
    assert finer_axis([1.0, 2.5, 4.0]) == [(1.0, True), (1.75, False), (2.5, True), (3.25, False), (4.0, True)]
    assert finer_axis([12.0]) == [(12.0, True)]


def test_validation_points_cover_the_finer_grid_with_their_kinds():
    axes = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]}
    points = validation_points(axes)
    assert len(points) == 5 * 3 * 1  # 2n-1 per axis of length n > 1
    grid = {(op.torque_nm, op.speed_rpm) for op, kind in points if kind == "grid"}
    assert grid == {(t, n) for t in axes["torque_nm"] for n in axes["speed_rpm"]}
    assert sum(1 for _, kind in points if kind == "midpoint") == 15 - 6
    assert (OperatingPoint(torque_nm=1.75, speed_rpm=1500.0, udc_v=12.0), "midpoint") in points
    # torque changes slowest after U_dc (a torque step costs the most settling), speed innermost, its direction
    # alternating: consecutive points differ by one speed step
    torques = [op.torque_nm for op, _ in points]
    assert torques == sorted(torques)
    assert [op.speed_rpm for op, _ in points[:6]] == [1000.0, 1500.0, 2000.0, 2000.0, 1500.0, 1000.0]
    for (a, _), (b, _) in zip(points, points[1:]):
        assert (a.torque_nm == b.torque_nm) != (a.speed_rpm == b.speed_rpm)


def test_settling_order_steps_speed_innermost_and_alternates():
    ops = [
        OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u)
        for u, n, t in [(24, 1000, 2), (12, 1100, 2), (12, 1000, 1), (12, 1100, 1), (12, 1000, 2), (24, 1100, 2)]
    ]
    got = [(op.udc_v, op.torque_nm, op.speed_rpm) for op in settling_order(ops)]
    # U_dc, then torque rows; each row's speeds reverse the last row's direction (also across a U_dc change)
    assert got == [(12, 1, 1000), (12, 1, 1100), (12, 2, 1100), (12, 2, 1000), (24, 2, 1000), (24, 2, 1100)]
    assert sorted(settling_order(ops), key=lambda op: op.model_dump_json()) == sorted(
        ops, key=lambda op: op.model_dump_json()
    )


def _cell(kind, db=None, status="measured", t=1.0):
    c = {
        "operating_point": {"torque_nm": t, "speed_rpm": 1000.0, "udc_v": 12.0},
        "kind": kind,
        "status": status,
        "error": None if status == "measured" else "MeasurementError: boom",
    }
    if status == "measured":
        c.update(suppression_db=db, plant_time_s=0.5, at_noise_floor=db > 50)
    return c


def test_summary_counts_failed_cells_apart_and_never_as_a_number():
    cells = [
        _cell("grid", 40.0),
        _cell("grid", 52.0, t=2.0),
        _cell("grid", status="failed"),
        _cell("midpoint", 30.0),
        _cell("midpoint", 20.0, t=3.0),
        _cell("midpoint", 26.0),
        _cell("midpoint", status="not_measured"),
    ]
    s = summarize(cells)
    assert s["grid"] == {
        "cells": 3,
        "measured": 2,
        "failed": 1,
        "not_measured": 0,
        "at_noise_floor": 1,
        "median_db": 46.0,
        "min_db": 40.0,
    }
    assert s["midpoint"]["median_db"] == statistics.median([30.0, 20.0, 26.0]) and s["midpoint"]["min_db"] == 20.0
    assert s["midpoint"]["not_measured"] == 1
    assert s["worst"] == {
        "operating_point": {"torque_nm": 3.0, "speed_rpm": 1000.0, "udc_v": 12.0},
        "kind": "midpoint",
        "suppression_db": 20.0,
    }
    assert s["plant_time_s"] == pytest.approx(2.5)
    empty = summarize([_cell("grid", status="failed")])
    assert empty["grid"]["median_db"] is None and empty["worst"] is None


# `storage` (tests/conftest.py): every test here runs on SQLite and on PostgreSQL


def test_empty_and_partial_maps_are_refused_unless_forced(storage):
    full = build_map_from_sweep(storage, sweep_with_results(storage))
    check_validatable(storage, full, force=False)
    # one failed cell between ok ones carries the fill rule's entry: no hole while the fill goes in
    partial = build_map_from_sweep(storage, sweep_with_results(storage, failing={(2.5, 1000.0)}))
    check_validatable(storage, partial, force=False)
    with pytest.raises(ValidationRefused, match="1 of 4 cells are not ok.*force"):
        check_validatable(storage, partial, force=False, fill=False)
    check_validatable(storage, partial, force=True, fill=False)
    empty = build_map_from_sweep(
        storage, sweep_with_results(storage, failing={(1.0, 1000.0), (2.5, 1000.0), (1.0, 2000.0), (2.5, 2000.0)})
    )
    with pytest.raises(ValidationRefused, match="no valid"):
        check_validatable(storage, empty, force=True)


def _stored_validation(storage) -> tuple[int, int]:
    map_id = build_map_from_sweep(storage, sweep_with_results(storage))
    job_id = storage.create_job("validation", {"map_id": map_id, "force": False, "options": {}})
    run = ValidationRun(
        map_id=map_id, harmonic_order=6, options={}, download={"map_id": map_id, "bytes": 98, "crc32": "0x12345678"}
    )
    run.cells = [_cell("grid", 44.0), _cell("midpoint", 27.5, t=1.75)]
    store_validation(storage, job_id, run, "test-bench")
    return map_id, job_id


def test_the_map_keeps_its_latest_validation_and_every_export_carries_it(storage):
    map_id, job_id = _stored_validation(storage)
    m = map_public(storage, map_id).model_dump()
    assert m["validation"]["job_id"] == job_id and m["validation"]["grid"]["median_db"] == 44.0
    assert job_public(storage, storage.get_job(job_id)).validation.cells[1].suppression_db == 27.5
    line = (
        f"validated in the drive's LUT mode (job {job_id}, {m['validation']['finished_at']}, done): grid median "
        "44.0 dB, min 44.0 dB (1 of 1 measured); midpoint median 27.5 dB, min 27.5 dB (1 of 1 measured); "
        "worst 27.5 dB at 1.75 Nm, 1000 rpm, 12 V (midpoint)"
    )
    assert f"# {line}\n" in export_map(m, "csv")
    assert f" * {line}.\n" in export_map(m, "c")
    assert f"* {line}\n" in export_map(m, "dcm")
    assert json.loads(export_map(m, "json"))["validation"]["midpoint"]["min_db"] == 27.5
    assert "not validated in the drive's LUT mode" in export_map(
        map_public(storage, build_map_from_sweep(storage, sweep_with_results(storage))).model_dump(), "csv"
    )


def test_migration_6_rebuilds_jobs_keeping_every_row(tmp_path):
    """A database at schema 5 with jobs and results pointing at them: after 0006 every row is there,
    the results still point at their jobs, and jobs.kind takes 'validation' but nothing unknown."""
    db = tmp_path / "old.db"
    with sqlite3.connect(db) as conn:
        for number, path in migration_files()[:5]:
            conn.executescript(path.read_text())
        conn.execute("PRAGMA user_version = 5")
        conn.execute(
            "INSERT INTO jobs (kind, state, request_json, created_at) VALUES ('identification', 'done', '{}', 't')"
        )
        conn.execute("INSERT INTO jobs (kind, state, request_json, created_at) VALUES ('sweep', 'failed', '{}', 't')")
        row = encode_columns(
            "results", result_row(OP1_POINT, "adaptive", AdaptiveOptions(), "b", "t0", error="boom", job_id=1)
        )
        conn.execute(
            f"INSERT INTO results ({', '.join(row)}) VALUES ({', '.join('?' for _ in row)})", tuple(row.values())
        )
    storage = Storage(db)
    assert MIGRATIONS_DIR.joinpath("sqlite", "0006_map_validations.sql").exists()
    with sqlite3.connect(db) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(migration_files())
        assert conn.execute("SELECT id, kind, state FROM jobs ORDER BY id").fetchall() == [
            (1, "identification", "done"),
            (2, "sweep", "failed"),
        ]
        assert conn.execute("SELECT job_id FROM results").fetchall() == [(1,)]
        assert conn.execute("PRAGMA foreign_key_check").fetchall() == []
        with pytest.raises(sqlite3.IntegrityError):
            conn.execute(
                "INSERT INTO jobs (kind, state, request_json, created_at) VALUES ('bogus', 'queued', '{}', 't')"
            )
    assert storage.create_job("validation", {"map_id": 1}) == 3
