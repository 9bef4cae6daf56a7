"""The database engine a `--db` value names: a `postgresql://user@host:port/dbname` URL is the lab's
shared server (service/store/postgres_engine.py), anything else a SQLite file (the embedded default,
service/store/sqlite_engine.py). Storage speaks to either through the same few methods: connect,
transaction, migrate, close, and `claim` (who may run the database's unfinished work)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.store.sqlite_engine import SqliteEngine

if TYPE_CHECKING:
    from service.store.postgres_engine import PostgresEngine

URL_PREFIXES = ("postgresql://", "postgres://")


def is_server_url(location: str | Path) -> bool:
    return isinstance(location, str) and location.startswith(URL_PREFIXES)


def engine_class(location: str | Path) -> type[SqliteEngine] | type[PostgresEngine]:
    if is_server_url(location):
        from service.store.postgres_engine import PostgresEngine  # psycopg only where a server is named

        return PostgresEngine
    return SqliteEngine


def open_engine(
    location: str | Path, busy_timeout_s: float = 10.0, statement_timeout_s: float | None = None
) -> SqliteEngine | PostgresEngine:
    """`statement_timeout_s`: a server's bound on one statement (SQLite's only wait is its busy timeout)."""
    if not is_server_url(location):
        return SqliteEngine(location, busy_timeout_s)
    from service.store.postgres_engine import PostgresEngine  # psycopg only where a server is named

    if statement_timeout_s is not None:
        return PostgresEngine(str(location), busy_timeout_s, statement_timeout_s)
    return PostgresEngine(str(location), busy_timeout_s)


def database_claim(location: str | Path, port: int | None) -> Any:
    """The claim a serve takes before it migrates or recovers anything: a flock on a SQLite file; nothing
    on a shared server (each service claims only its own bench's jobs there)."""
    return engine_class(location).claim(str(location), port)


def display_location(location: str | Path) -> str:
    """The database as the log and the CLI name it (a server URL without its password)."""
    if is_server_url(location):
        from service.store.postgres_engine import public_location

        return public_location(str(location))
    return str(location)
