"""Shared by every test: the emulated bench runs as fast as its DAQ is read unless a test says otherwise.

The service's default is the real bench's clock (`emulator.speedup = 1`). Tests measure behaviour, not
bench time, so they run the emulator at speedup 0 (plant time stops while nobody reads: nothing is lost,
the same results) through the environment every service and CLI process of the session inherits; the
tests that prove real-time behaviour pass `--speedup 1` themselves (tests/e2e/test_realtime_e2e.py).

Fixtures shared by several modules:
- `live`: the real app around a started CalibrationService (tests/support/live_app.py), one per module:
  (service, TestClient, operator headers). A module passes settings overrides of its own in a
  module-level dict `LIVE_SETTINGS`.
- `pg_cluster` (one throwaway PostgreSQL server per session, tests/support/postgres.py) and `pg_url`
  (a fresh database on it per test).
- `db_location`, `storage`: a storage test once per engine, SQLite and PostgreSQL (`storage` migrated).

What the fixtures start ends with the session, also when pytest is killed (kill -9: no teardown runs):
the PostgreSQL server and the services with a parent-death signal (tests/support/parent_death.py), the
emulators when their stdin pipe closes (tests/e2e/test_session_cleanup_e2e.py proves it)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("RIPPLECAL_EMULATOR__SPEEDUP", "0")


@pytest.fixture(scope="module")
def live(request, tmp_path_factory):
    # imported here: the unit tests never need the application (nor its import time)
    from tests.support.live_app import bearer, client_for, started_service

    overrides = getattr(request.module, "LIVE_SETTINGS", {})
    name = request.module.__name__.rsplit(".", 1)[-1]
    with started_service(tmp_path_factory.mktemp(name), **overrides) as service:
        yield service, client_for(service), bearer(service, "operator")


@pytest.fixture(scope="session")
def pg_cluster():
    """A throwaway PostgreSQL server for the session (tests/support/postgres.py). Missing binaries fail
    the tests that need it, saying how to install them: a lab engine untested is not a pass."""
    from tests.support.postgres import PostgresCluster, PostgresMissing

    try:
        cluster = PostgresCluster().init()
    except PostgresMissing as exc:
        pytest.fail(str(exc), pytrace=False)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.remove()


@pytest.fixture
def pg_url(pg_cluster):
    """A fresh, empty database on the session's server: its postgresql:// URL. A test that stops the
    server starts it again before it ends."""
    if not pg_cluster.running:
        pg_cluster.start()
    return pg_cluster.create_database()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_location(request, tmp_path):
    """The database of a storage test, once per engine: a new SQLite file, or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        return str(tmp_path / "storage.db")
    return request.getfixturevalue("pg_url")


@pytest.fixture
def storage(db_location):
    """A migrated Storage on each engine (a module may define its own `storage` instead)."""
    from service.store.storage import Storage

    storage = Storage(db_location)
    yield storage
    storage.close()
