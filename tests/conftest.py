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

import gc
import os
import time

import pytest

os.environ.setdefault("RIPPLECAL_EMULATOR__SPEEDUP", "0")

# The in-process services of the suite produce their CAN heartbeat from a thread of this process: a garbage
# collection pause longer than the drive's consumer time (500 ms) reads to the emulated drive as a silent service
# (EMCY 0x8130, a fault only a person resets). The heap of a whole collected suite is frozen out of the collector's
# scans, and the longest pause is said at the end, so a lost heartbeat can be told from a stalled process.
_gc_pause = {"started": 0.0, "longest_s": 0.0, "generation": -1}


def _time_gc(phase: str, info: dict) -> None:
    if phase == "start":
        _gc_pause["started"] = time.perf_counter()
        return
    pause_s = time.perf_counter() - _gc_pause["started"]
    if pause_s > _gc_pause["longest_s"]:
        _gc_pause["longest_s"], _gc_pause["generation"] = pause_s, info.get("generation", -1)


def pytest_collection_finish(session) -> None:
    gc.collect()
    gc.freeze()  # what collection built lives for the session: not scanned by every later full collection
    gc.callbacks.append(_time_gc)


def pytest_terminal_summary(terminalreporter) -> None:
    terminalreporter.write_line(
        f"longest garbage-collection pause of the test process: {_gc_pause['longest_s'] * 1000:.0f} ms "
        f"(generation {_gc_pause['generation']}); the drives' heartbeat consumer time is 500 ms"
    )


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
