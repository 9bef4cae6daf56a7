"""The lab engine: one PostgreSQL database for every bench of a lab, through psycopg 3 and a small
connection pool. Storage's SQL (with `?` placeholders, service/store/dialect.py) runs here unchanged;
an INSERT into a table with an `id` gets `RETURNING id`, so `cursor.lastrowid` works as on SQLite.
The schema version lives in a table (schema_version), migrated under an advisory lock so two services
starting at once do not both migrate. A lost server is StorageUnavailable("unreachable"): what needs
the database waits and tries again, and the pool reconnects by itself.

Every call is bounded: the server ends a statement past statement_timeout (and a transaction left idle
past idle_in_transaction_session_timeout), and the client bounds the answer itself (`_Deadlines`): a
server or session that hangs (a frozen backend answers nothing, yet its kernel keeps the TCP connection
alive, so keepalives do not notice) has its connection shut under the waiting call, which then fails as
StorageUnavailable("timeout") instead of holding its thread (the engine's worker, an API request) for good."""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence, cast

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

log = logging.getLogger(__name__)
CONNECT_TIMEOUT_S = 5  # one connection attempt to the server (libpq's connect_timeout)
POOL_MIN, POOL_MAX = 1, 8  # one service: its engine worker, the API's threads, the scheduler
# the pool's reconnection attempts back off (1, 2, 4 s ...) for this long, then stop until a call needs
# a connection again: a server back after a long outage is found within seconds, not after a long backoff
RECONNECT_WINDOW_S = 10.0
# the pool logs each failed reconnection attempt (two lines each); the service names an unavailable
# database itself, once per retry (StorageUnavailable), so only the pool's errors are worth a line
logging.getLogger("psycopg.pool").setLevel(logging.ERROR)
# what synchronous_commit may be: each waits for the commit's WAL on the server's own disk (_check_durability)
DURABLE_SYNCHRONOUS_COMMIT = frozenset({"on", "local", "remote_write", "remote_apply"})
MIGRATION_LOCK_KEY = 0x72697070  # pg_advisory_xact_lock key of ripplecal's migrations ("ripp")
MIGRATION_LOCK_WAIT_S = 60  # another service migrating (or the tables' other users) is waited for this long
STATEMENT_TIMEOUT_S = 5.0  # default bound of one statement (settings.server.db_statement_timeout_s)
# the client's bound on one statement's answer: the server's own timeout first, this margin after it (the
# server answers its timeout itself; only a server or session that hangs is cut off by the client)
CLIENT_MARGIN_S = 1.0
DEADLINE_POLL_S = 0.1  # how often the client's bounds are looked at
KNOWN_UNAVAILABLE_S = 30.0  # a failed call is taken as the database's state this long (unless one succeeds)
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
    "57014": ("timeout", "a statement ran past its statement_timeout"),  # query_canceled
    "25P03": ("timeout", "a transaction stayed idle past idle_in_transaction_session_timeout"),
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

    def __iter__(self) -> Iterator[Any]:
        return iter(self._values)

    def keys(self) -> list[str]:
        return list(self._names)

    def __repr__(self) -> str:
        return f"Row({dict(zip(self._names, self._values))!r})"


def _row_factory(cursor: psycopg.Cursor[Any]) -> Callable[[Sequence[Any]], Row]:
    names = {col.name: i for i, col in enumerate(cursor.description or ())}
    return lambda values: Row(names, values)


class Cursor:
    """What Storage uses of sqlite3's cursor: fetchone, fetchall, iteration, rowcount, lastrowid."""

    def __init__(self, cursor: psycopg.Cursor[Row], lastrowid: int | None = None):
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

    def __init__(self, conn: psycopg.Connection, id_tables: frozenset[str], renew: Callable[[], None] = lambda: None):
        self.raw = conn  # the psycopg connection itself (the engine's transactions and migrations)
        self._id_tables = id_tables
        self._renew = renew  # each statement gets the client's full bound on its answer

    def execute(self, sql: str, params: Sequence[Any] = ()) -> Cursor:
        self._renew()
        m = _INSERT_INTO.match(sql)
        returning = m is not None and m.group(1).lower() in self._id_tables and "RETURNING" not in sql.upper()
        cur = self.raw.cursor(row_factory=_row_factory)
        cur.execute(format_placeholders(sql + (" RETURNING id" if returning else "")), tuple(params))
        lastrowid = None
        if returning:
            row = cur.fetchone()
            lastrowid = row[0] if row is not None else None
        return Cursor(cur, lastrowid)

    def executemany(self, sql: str, seq_of_params: Iterable[Sequence[Any]]) -> Cursor:
        self._renew()
        cur = self.raw.cursor(row_factory=_row_factory)
        cur.executemany(format_placeholders(sql), [tuple(p) for p in seq_of_params])
        return Cursor(cur)


class PostgresEngine:
    dialect = POSTGRESQL
    path = None  # no file

    def __init__(self, url: str, busy_timeout_s: float = 10.0, statement_timeout_s: float = STATEMENT_TIMEOUT_S):
        self.location = public_location(url)  # what the log, the CLI and answers name: no password
        self.busy_timeout_s = busy_timeout_s  # a lock or a free connection is waited for this long
        self.statement_timeout_s = statement_timeout_s
        self._answer_bound_s = statement_timeout_s + CLIENT_MARGIN_S  # the client's own bound (module doc)
        self._deadlines = _Deadlines()
        self._unavailable: tuple[float, StorageUnavailable] | None = None  # (monotonic, why): the last call failed
        self._id_tables: frozenset[str] = frozenset()
        self._pool = ConnectionPool(
            url,
            min_size=POOL_MIN,
            max_size=POOL_MAX,
            # a free connection is waited for no longer than a statement's answer: a server that hangs (no
            # new session starts) is said in seconds, not after every lock's patience
            timeout=min(busy_timeout_s, self._answer_bound_s),
            reconnect_timeout=RECONNECT_WINDOW_S,
            open=False,
            check=self._check,  # a connection the server dropped is replaced, not handed out
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
                "options": " ".join(
                    [
                        f"-c lock_timeout={int(busy_timeout_s * 1000)}",
                        f"-c statement_timeout={int(statement_timeout_s * 1000)}",
                        # a transaction never left open by a client that hangs holds no lock for long
                        f"-c idle_in_transaction_session_timeout={int((statement_timeout_s + 2 * CLIENT_MARGIN_S) * 1000)}",
                    ]
                ),
            },
            name="ripplecal",
        )
        try:
            self._pool.open(wait=True, timeout=max(busy_timeout_s, CONNECT_TIMEOUT_S))
        except psycopg.Error as exc:
            self._pool.close()
            raise self._unavailable_or(self._why_not(url, exc)) from exc
        self._deadlines.start()
        try:
            self._check_durability(str(conninfo_to_dict(url).get("dbname") or "the database"))
        except BaseException:
            self.close()
            raise

    @property
    def files_directory(self) -> Path:
        """Files that belong with the database (recordings) cannot live on its server: the user's data
        directory, where the default SQLite file would be."""
        return Path(default_db_path()).parent

    @staticmethod
    def claim(location: str, port: int | None) -> _NoClaim:
        """Many services share one server: each claims its bench's jobs, not the database (no file claim)."""
        return _NoClaim()

    @staticmethod
    def _configure(conn: psycopg.Connection) -> None:
        # NUMERIC (SUM or AVG of integers) read as float, as SQLite gives it
        conn.adapters.register_loader("numeric", FloatLoader)
        # flags are INTEGER 0/1 on both engines (SQLite has no BOOLEAN): a Python bool written as one
        conn.adapters.register_dumper(bool, _BoolAsInteger)

    def _check_durability(self, dbname: str) -> None:
        """StorageError (the service refuses to start) unless a commit is on the server's disk before the
        server acknowledges it: a result, a point or a sweep's state the service reported stored must
        survive the server's crash. synchronous_commit `off` acknowledges first (a kill -9 of the
        postmaster lost a sweep's last point, the sweep left `done`); `local`, `on`, `remote_write` and
        `remote_apply` all wait for the local WAL flush (the remote ones wait for a standby as well), so
        all four keep it. As the session sees it: the server's, the database's or the role's setting, or
        the URL's options. fsync off is only warned of: an operating-system crash, not a server's, loses
        data then, and a server without it is an administrator's deliberate choice."""
        with self.connect() as conn:
            row = conn.execute("SELECT current_setting('synchronous_commit'), current_setting('fsync')").fetchone()
        assert row is not None  # a SELECT without FROM: one row
        synchronous_commit, fsync = row[0], row[1]
        if synchronous_commit not in DURABLE_SYNCHRONOUS_COMMIT:
            raise StorageError(
                f"database {self.location} has synchronous_commit = {synchronous_commit}: the server says a commit "
                "is done before it is on disk, so a server crash loses results the service reported stored; "
                f'set it on (ALTER DATABASE "{dbname}" SET synchronous_commit = on, or in postgresql.conf) '
                "and start again"
            )
        if fsync != "on":
            log.warning(
                "database %s has fsync = %s: an operating-system crash or power loss can lose or corrupt it",
                self.location,
                fsync,
            )

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

    def _check(self, conn: psycopg.Connection) -> None:
        """The pool's check of a connection before it is handed out, bounded as any statement."""
        with self._deadlines.watch(conn, self._answer_bound_s):
            ConnectionPool.check_connection(conn)

    @contextlib.contextmanager
    def connect(self, answer_bound_s: float | None = None) -> Iterator[Connection]:
        """A pooled connection, each statement its own transaction, each answer bounded (module doc;
        `answer_bound_s`: another bound than the statement timeout's); a psycopg error that passes (the
        server lost, a pool that waited in vain, a lock timeout, no answer in time) becomes StorageUnavailable."""
        bound_s = answer_bound_s or self._answer_bound_s
        watch = None
        try:
            with self._pool.connection() as conn:
                with self._deadlines.watch(conn, bound_s) as watch:
                    yield Connection(conn, self._id_tables, renew=watch.renew)
        except psycopg.Error as exc:
            if watch is not None and watch.cut:
                passing: StorageUnavailable | None = StorageUnavailable(
                    "timeout",
                    f"database {self.location}: no answer within {bound_s:g} s (the server or its session "
                    "hangs); its connection was closed",
                )
            else:
                passing = unavailable(exc, self.location)
            if passing is not None:
                self._unavailable = (time.monotonic(), passing)
                raise passing from exc
            raise
        self._unavailable = None

    def known_unavailable(self) -> StorageUnavailable | None:
        """Why the last call failed, if it failed within KNOWN_UNAVAILABLE_S and none has succeeded since:
        what must answer at once (a cancel, a known token) need not wait for the server to say it again."""
        last = self._unavailable
        if last is None or time.monotonic() - last[0] > KNOWN_UNAVAILABLE_S:
            return None
        return last[1]

    @contextlib.contextmanager
    def transaction(self) -> Iterator[Connection]:
        with self.connect() as conn, conn.raw.transaction():
            yield conn

    def migrate(self, available: list[Migration]) -> int:
        """Apply the numbered migrations the database has not seen, in one transaction under an advisory
        lock (a second service starting at once waits, then finds nothing to do); its version after."""
        with self.connect(answer_bound_s=MIGRATION_LOCK_WAIT_S + 30.0) as conn, conn.raw.transaction():
            conn.execute(f"SET LOCAL lock_timeout = '{MIGRATION_LOCK_WAIT_S}s'")
            conn.execute(f"SET LOCAL statement_timeout = '{MIGRATION_LOCK_WAIT_S + 20}s'")
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
            version: int = cast(Row, conn.execute("SELECT version FROM schema_version").fetchone())[0]
            tables = conn.execute(
                "SELECT table_name FROM information_schema.columns WHERE table_schema = current_schema() "
                "AND column_name = 'id'"
            ).fetchall()
        self._id_tables = frozenset(r[0] for r in tables)
        return version

    def close(self) -> None:
        self._pool.close()
        self._deadlines.stop()


class _Watch:
    """One connection in use, and the monotonic time by which its current statement must be answered."""

    def __init__(self, conn: psycopg.Connection, bound_s: float):
        self.conn = conn
        self.bound_s = bound_s
        self.deadline = time.monotonic() + bound_s
        self.cut = False  # its connection was shut because the answer did not come in time

    def renew(self) -> None:
        self.deadline = time.monotonic() + self.bound_s


class _Deadlines:
    """The client's own bound on the server's answers (module doc): one thread shuts the socket of a
    connection whose statement is past its deadline, so the call waiting on it fails at once (psycopg
    then reports the connection lost, and the pool drops it). A socket's shutdown, unlike a close, is
    safe while another thread waits on it."""

    def __init__(self) -> None:
        self._watches: set[_Watch] = set()
        self._lock = threading.Lock()  # held only to add, remove and list the watches: never across I/O
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="ripplecal-db-deadlines", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    @contextlib.contextmanager
    def watch(self, conn: psycopg.Connection, bound_s: float) -> Iterator[_Watch]:
        w = _Watch(conn, bound_s)
        with self._lock:
            self._watches.add(w)
        try:
            yield w
        finally:
            with self._lock:
                self._watches.discard(w)

    def _run(self) -> None:
        while not self._stop.wait(DEADLINE_POLL_S):
            now = time.monotonic()
            with self._lock:
                late = [w for w in self._watches if not w.cut and w.deadline < now]
            for w in late:
                w.cut = True
                _shut(w.conn)


def _shut(conn: psycopg.Connection) -> None:
    """Shut the connection's socket both ways (a dup of its descriptor: the connection closes its own)."""
    try:
        fd = conn.pgconn.socket
        with socket.socket(fileno=socket.dup(fd)) as sock:
            sock.shutdown(socket.SHUT_RDWR)
    except (OSError, psycopg.Error) as exc:
        logging.getLogger(__name__).debug("a late connection could not be shut: %s", exc)


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
