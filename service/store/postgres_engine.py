"""The lab engine: one PostgreSQL database for every bench of a lab, through psycopg 3 and a small
connection pool. Storage's SQL (with `?` placeholders, service/store/dialect.py) runs here unchanged;
an INSERT into a table with an `id` gets `RETURNING id`, so `cursor.lastrowid` works as on SQLite.
The schema version lives in a table (schema_version), migrated under an advisory lock so two services
starting at once do not both migrate. A lost server is StorageUnavailable("unreachable"): what needs
the database waits and tries again, and the pool reconnects by itself."""

from __future__ import annotations

import contextlib
import logging
import re
from pathlib import Path
from typing import Any, Iterator, Sequence

import psycopg
from psycopg.adapt import Dumper
from psycopg.conninfo import conninfo_to_dict
from psycopg.pq import Format
from psycopg.types.numeric import FloatLoader
from psycopg_pool import ConnectionPool

from service.settings import default_db_path
from service.store.dialect import POSTGRESQL, format_placeholders
from service.store.errors import StorageError, StorageUnavailable
from service.store.migrations import Migration, check_not_newer

CONNECT_TIMEOUT_S = 5  # one connection attempt to the server (libpq's connect_timeout)
POOL_MIN, POOL_MAX = 1, 8  # one service: its engine worker, the API's threads, the scheduler
# the pool's reconnection attempts back off (1, 2, 4 s ...) for this long, then stop until a call needs
# a connection again: a server back after a long outage is found within seconds, not after a long backoff
RECONNECT_WINDOW_S = 10.0
# the pool logs each failed reconnection attempt (two lines each); the service names an unavailable
# database itself, once per retry (StorageUnavailable), so only the pool's errors are worth a line
logging.getLogger("psycopg.pool").setLevel(logging.ERROR)
MIGRATION_LOCK_KEY = 0x72697070  # pg_advisory_xact_lock key of ripplecal's migrations ("ripp")
MIGRATION_LOCK_WAIT_S = 60  # another service migrating (or the tables' other users) is waited for this long
_INSERT_INTO = re.compile(r"^\s*INSERT\s+INTO\s+([a-z_]+)", re.IGNORECASE)

# SQLSTATEs of the causes that pass, and what to tell the operator (class 08: connection exceptions)
_UNAVAILABLE_STATES = {
    "57P01": ("unreachable", "the server is shutting down"),  # admin_shutdown
    "57P02": ("unreachable", "the server crashed"),  # crash_shutdown
    "57P03": ("unreachable", "the server is starting up"),  # cannot_connect_now
    "53100": ("disk_full", "its disk is full"),
    "53300": ("unreachable", "the server has too many connections"),
    "25006": ("read_only", "the server is read-only"),
    "55P03": ("locked", "a lock is held by another session"),  # lock_not_available (lock_timeout)
    "58030": ("io_error", "an I/O error on the server"),
}


def public_location(url: str) -> str:
    """postgresql://user@host:port/dbname: the URL without its password (nor other parameters)."""
    info = conninfo_to_dict(url)
    user = f"{info['user']}@" if info.get("user") else ""
    return f"postgresql://{user}{info.get('host', 'localhost')}:{info.get('port', 5432)}/{info.get('dbname', '')}"


def unavailable(exc: BaseException, location: str) -> StorageUnavailable | None:
    """The StorageUnavailable a psycopg error stands for (None: not one that passes)."""
    if not isinstance(exc, psycopg.OperationalError):
        return None
    state = getattr(exc, "sqlstate", None)
    if state in _UNAVAILABLE_STATES:
        cause, what = _UNAVAILABLE_STATES[state]
    elif state is None or state.startswith("08"):  # refused, lost, a pool that waited in vain
        cause, what = "unreachable", "the server cannot be reached"
    else:
        return None
    detail = " ".join(str(exc).split())
    message = f"database {location}: {what} ({detail})"
    return StorageUnavailable(cause, message, public=message)


class Row:
    """A result row read as sqlite3.Row is: by position or by column name, with keys()."""

    __slots__ = ("_names", "_values")

    def __init__(self, names: dict[str, int], values: Sequence[Any]):
        self._names = names
        self._values = values

    def __getitem__(self, key: int | str) -> Any:
        return self._values[self._names[key] if isinstance(key, str) else key]

    def __len__(self) -> int:
        return len(self._values)

    def __iter__(self):
        return iter(self._values)

    def keys(self) -> list[str]:
        return list(self._names)

    def __repr__(self) -> str:
        return f"Row({dict(zip(self._names, self._values))!r})"


def _row_factory(cursor: psycopg.Cursor):
    names = {col.name: i for i, col in enumerate(cursor.description or ())}
    return lambda values: Row(names, values)


class Cursor:
    """What Storage uses of sqlite3's cursor: fetchone, fetchall, iteration, rowcount, lastrowid."""

    def __init__(self, cursor: psycopg.Cursor, lastrowid: int | None = None):
        self._cursor = cursor
        self.lastrowid = lastrowid
        self.rowcount = cursor.rowcount

    def fetchone(self) -> Row | None:
        return self._cursor.fetchone() if self._cursor.description else None

    def fetchall(self) -> list[Row]:
        return self._cursor.fetchall() if self._cursor.description else []

    def __iter__(self) -> Iterator[Row]:
        return iter(self.fetchall())


class Connection:
    """A pooled psycopg connection speaking Storage's SQL (`?` placeholders, lastrowid)."""

    def __init__(self, conn: psycopg.Connection, id_tables: frozenset[str]):
        self.raw = conn  # the psycopg connection itself (the engine's transactions and migrations)
        self._id_tables = id_tables

    def execute(self, sql: str, params: Sequence[Any] = ()) -> Cursor:
        m = _INSERT_INTO.match(sql)
        returning = m is not None and m.group(1).lower() in self._id_tables and "RETURNING" not in sql.upper()
        cur = self.raw.cursor(row_factory=_row_factory)
        cur.execute(format_placeholders(sql + (" RETURNING id" if returning else "")), tuple(params))
        lastrowid = None
        if returning:
            row = cur.fetchone()
            lastrowid = row[0] if row is not None else None
        return Cursor(cur, lastrowid)

    def executemany(self, sql: str, seq_of_params) -> Cursor:
        cur = self.raw.cursor(row_factory=_row_factory)
        cur.executemany(format_placeholders(sql), [tuple(p) for p in seq_of_params])
        return Cursor(cur)


class PostgresEngine:
    dialect = POSTGRESQL
    path = None  # no file

    def __init__(self, url: str, busy_timeout_s: float = 10.0):
        self.location = public_location(url)  # what the log, the CLI and answers name: no password
        self.busy_timeout_s = busy_timeout_s  # a lock or a free connection is waited for this long
        self._id_tables: frozenset[str] = frozenset()
        self._pool = ConnectionPool(
            url,
            min_size=POOL_MIN,
            max_size=POOL_MAX,
            timeout=busy_timeout_s,
            reconnect_timeout=RECONNECT_WINDOW_S,
            open=False,
            check=ConnectionPool.check_connection,  # a connection the server dropped is replaced, not handed out
            configure=self._configure,
            kwargs={
                "autocommit": True,  # one statement, one transaction, as SQLite's isolation_level=None
                "connect_timeout": CONNECT_TIMEOUT_S,
                "application_name": "ripplecal",
                # a lost server is noticed on an idle connection too, within about 10 s
                "keepalives": 1,
                "keepalives_idle": 5,
                "keepalives_interval": 2,
                "keepalives_count": 3,
                "tcp_user_timeout": 10_000,  # ms: data the server never acknowledges fails the connection
                "options": f"-c lock_timeout={int(busy_timeout_s * 1000)}",
            },
            name="ripplecal",
        )
        try:
            self._pool.open(wait=True, timeout=max(busy_timeout_s, CONNECT_TIMEOUT_S))
        except psycopg.Error as exc:
            self._pool.close()
            raise self._unavailable_or(self._why_not(url, exc)) from exc

    @property
    def files_directory(self) -> Path:
        """Files that belong with the database (recordings) cannot live on its server: the user's data
        directory, where the default SQLite file would be."""
        return Path(default_db_path()).parent

    @staticmethod
    def claim(location: str, port: int | None):
        """Many services share one server: each claims its bench's jobs, not the database (no file claim)."""
        return _NoClaim()

    @staticmethod
    def _configure(conn: psycopg.Connection) -> None:
        # NUMERIC (SUM or AVG of integers) read as float, as SQLite gives it
        conn.adapters.register_loader("numeric", FloatLoader)
        # flags are INTEGER 0/1 on both engines (SQLite has no BOOLEAN): a Python bool written as one
        conn.adapters.register_dumper(bool, _BoolAsInteger)

    @staticmethod
    def _why_not(url: str, pool_error: BaseException) -> BaseException:
        """The server's own refusal (refused, unknown database, authentication) rather than the pool's
        "initialization incomplete": one direct connection attempt says it."""
        try:
            psycopg.connect(url, connect_timeout=CONNECT_TIMEOUT_S).close()
        except psycopg.Error as exc:
            return exc
        return pool_error

    def _unavailable_or(self, exc: BaseException) -> BaseException:
        passing = unavailable(exc, self.location)
        return passing if passing is not None else exc

    @contextlib.contextmanager
    def connect(self) -> Iterator[Connection]:
        """A pooled connection, each statement its own transaction; a psycopg error that passes (the
        server lost, a pool that waited in vain, a lock timeout) becomes StorageUnavailable."""
        try:
            with self._pool.connection() as conn:
                yield Connection(conn, self._id_tables)
        except psycopg.Error as exc:
            passing = unavailable(exc, self.location)
            if passing is not None:
                raise passing from exc
            raise

    @contextlib.contextmanager
    def transaction(self) -> Iterator[Connection]:
        with self.connect() as conn, conn.raw.transaction():
            yield conn

    def migrate(self, available: list[Migration]) -> int:
        """Apply the numbered migrations the database has not seen, in one transaction under an advisory
        lock (a second service starting at once waits, then finds nothing to do); its version after."""
        with self.transaction() as conn:
            conn.execute(f"SET LOCAL lock_timeout = '{MIGRATION_LOCK_WAIT_S}s'")
            conn.execute("SELECT pg_advisory_xact_lock(?)", (MIGRATION_LOCK_KEY,))
            conn.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            row = conn.execute("SELECT version FROM schema_version").fetchone()
            if row is None:
                conn.execute("INSERT INTO schema_version (version) VALUES (0)")
            current = row[0] if row is not None else 0
            check_not_newer(self.location, current, available)
            for migration in available[current:]:
                try:
                    with conn.raw.transaction():  # a savepoint: the error names its migration
                        for statement in migration.statements:
                            conn.raw.execute(statement)
                except psycopg.Error as exc:
                    if unavailable(exc, self.location) is not None:
                        raise
                    raise StorageError(f"migration {migration.name} failed: {exc}") from exc
                conn.execute("UPDATE schema_version SET version = ?", (migration.number,))
            version = conn.execute("SELECT version FROM schema_version").fetchone()[0]
            tables = conn.execute(
                "SELECT table_name FROM information_schema.columns WHERE table_schema = current_schema() "
                "AND column_name = 'id'"
            ).fetchall()
        self._id_tables = frozenset(r[0] for r in tables)
        return version

    def close(self) -> None:
        self._pool.close()


class _BoolAsInteger(Dumper):
    """True/False as the INTEGER 1/0 of the schema's flag columns."""

    format = Format.TEXT
    oid = psycopg.postgres.types["int4"].oid

    def dump(self, obj: bool) -> bytes:
        return b"1" if obj else b"0"


class _NoClaim:
    """No database claim on a shared server (service/store/db_claim.py is SQLite's)."""

    def acquire(self) -> None:
        pass

    def release(self) -> None:
        pass
