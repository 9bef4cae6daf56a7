"""The numbered migrations on both engines: from empty, from an older schema with data in it, two
services migrating one PostgreSQL database at once, and the same tables and columns on both."""

from __future__ import annotations

import sqlite3
import threading

import psycopg
import pytest

from service.store.migrations import ENGINES, load_migrations, migration_files
from service.store.storage import Storage


def _sqlite_columns(path) -> dict[str, set[str]]:
    with sqlite3.connect(path) as conn:
        tables = [
            r[0]
            for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")
        ]
        return {t: {r[1] for r in conn.execute(f"PRAGMA table_info({t})")} for t in tables}


def _postgres_columns(url) -> dict[str, set[str]]:
    columns: dict[str, set[str]] = {}
    with psycopg.connect(url) as conn:
        for table, column in conn.execute(
            "SELECT table_name, column_name FROM information_schema.columns WHERE table_schema = 'public'"
        ):
            columns.setdefault(table, set()).add(column)
    columns.pop("schema_version")  # PostgreSQL's stand-in for PRAGMA user_version
    return columns


def test_every_number_has_a_common_file_or_one_per_engine():
    numbers = {engine: [n for n, _ in migration_files(engine)] for engine in ENGINES}
    assert numbers["sqlite"] == numbers["postgresql"] == list(range(1, len(migration_files()) + 1))


def test_all_migrations_apply_from_empty(storage):  # on each engine (tests/conftest.py)
    assert storage.migrate() == len(migration_files())
    assert storage.list_jobs() == [] and storage.list_sweeps() == [] and storage.list_maps() == []


def test_the_schema_has_the_same_tables_and_columns_on_both_engines(tmp_path, pg_url):
    Storage(tmp_path / "s.db").close()
    Storage(pg_url).close()
    assert _sqlite_columns(tmp_path / "s.db") == _postgres_columns(pg_url)


def _old_database_with_data(run) -> None:
    """A sweep with one result, written as schema 2's code wrote them."""
    run(
        "INSERT INTO sweeps (id, state, method, harmonic_order, grid_json, options_json, total_points, bench_identity, "
        "software_version, created_at) VALUES (1, 'running', 'adaptive', 6, '{}', '{}', 1, 'b', 'v0', 't0')"
    )
    run(
        "INSERT INTO jobs (id, kind, state, request_json, sweep_id, created_at) VALUES (1, 'sweep', 'done', '{}', 1, 't0')"
    )
    run(
        "INSERT INTO results (id, job_id, sweep_id, torque_nm, speed_rpm, udc_v, harmonic_order, method, options_json, "
        "status, suppression_db, bench_identity, software_version, started_at, finished_at) "
        "VALUES (1, 1, 1, 2.5, 2000.0, 12.0, 6, 'adaptive', '{}', 'ok', 45.5, 'b', 'v0', 't0', 't1')"
    )


def _check_the_data_survived(storage: Storage) -> None:
    assert storage.get_sweep(1)["state"] == "running" and storage.get_sweep(1)["kind"] == "sweep"
    [result] = storage.sweep_results(1)
    assert (result["job_id"], result["status"], result["suppression_db"]) == (1, "ok", 45.5)
    assert result["recording"] is None and result["superseded_by"] is None
    # new rows take ids after the old ones (SQLite's rowid, PostgreSQL's identity: see below)
    assert storage.create_job("validation", {}) > 1


def test_an_older_sqlite_database_with_data_migrates(tmp_path):
    db = tmp_path / "old.db"
    with sqlite3.connect(db) as conn:
        for migration in load_migrations("sqlite")[:2]:
            for statement in migration.statements:
                conn.execute(statement)
        conn.execute("PRAGMA user_version = 2")
        _old_database_with_data(conn.execute)
    storage = Storage(db)
    with sqlite3.connect(db) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(migration_files())
        assert conn.execute("PRAGMA foreign_key_check").fetchall() == []
    _check_the_data_survived(storage)


def test_an_older_postgresql_database_with_data_migrates(pg_url):
    with psycopg.connect(pg_url, autocommit=True) as conn:
        for migration in load_migrations("postgresql")[:2]:
            for statement in migration.statements:
                conn.execute(statement)
        conn.execute("CREATE TABLE schema_version (version INTEGER NOT NULL)")
        conn.execute("INSERT INTO schema_version (version) VALUES (2)")
        _old_database_with_data(conn.execute)
        # rows written with explicit ids (as by a copy from SQLite): the identities move past them
        for table in ("sweeps", "jobs", "results"):
            conn.execute(f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), (SELECT MAX(id) FROM {table}))")
    storage = Storage(pg_url)
    try:
        _check_the_data_survived(storage)
    finally:
        storage.close()


def test_two_services_migrating_one_postgresql_database_at_once(pg_url):
    """The advisory lock: one migrates, the other waits and finds the schema current."""
    opened, errors = [], []

    def start() -> None:
        try:
            opened.append(Storage(pg_url))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=start) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    try:
        assert errors == [] and len(opened) == 2
        assert [s.migrate() for s in opened] == [len(migration_files())] * 2
    finally:
        for s in opened:
            s.close()


def test_a_newer_postgresql_database_is_refused(pg_url):
    Storage(pg_url).close()
    with psycopg.connect(pg_url, autocommit=True) as conn:
        conn.execute("UPDATE schema_version SET version = 999")
    with pytest.raises(Exception, match="newer than this software"):
        Storage(pg_url)


@pytest.mark.parametrize(
    "column, good, bad",
    [("kind", "refinement", "bogus"), ("state", "cancelled", "lost")],
)
def test_the_checks_take_and_refuse_the_same_values_on_both_engines(storage, column, good, bad):
    """The CHECKs SQLite rebuilt its tables for are the ones PostgreSQL altered in place."""
    values = {"kind": "identification", "state": "queued", column: good}

    def insert(v: dict) -> None:
        with storage.transaction() as conn:
            conn.execute(
                "INSERT INTO jobs (kind, state, request_json, created_at) VALUES (?, ?, '{}', 't')",
                (v["kind"], v["state"]),
            )

    insert(values)
    with pytest.raises(Exception, match="(?i)check"):
        insert({**values, column: bad})
    sweep_id = storage.create_sweep("probe", 6, {}, {}, 1, "b", "v")
    storage.update_sweep(sweep_id, state="interrupted", pause_reason="shutdown")
    with pytest.raises(Exception, match="(?i)check"):
        storage.update_sweep(sweep_id, state="lost")
