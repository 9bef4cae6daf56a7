"""The embedded engine: one SQLite file. One connection per call, WAL mode, every write in one
transaction (BEGIN IMMEDIATE, one writer per process); the schema version in PRAGMA user_version."""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from service.store.dialect import SQLITE
from service.store.errors import StorageError, StorageUnavailable
from service.store.migrations import Migration, check_not_newer

if TYPE_CHECKING:
    from service.store.db_claim import DatabaseClaim

# sqlite3's OperationalError texts of the causes that pass, and what to tell the operator
_UNAVAILABLE = (
    ("database is locked", "locked", "another process holds its lock"),
    ("readonly database", "read_only", "its filesystem is read-only"),
    ("read-only", "read_only", "its filesystem is read-only"),
    ("database or disk is full", "disk_full", "its disk is full"),
    ("disk i/o error", "io_error", "a disk I/O error"),
    ("unable to open database file", "cannot_open", "the file cannot be opened"),
)


def unavailable(exc: BaseException, path: Path) -> StorageUnavailable | None:
    """The StorageUnavailable a sqlite3 error stands for (None: not one that passes)."""
    if not isinstance(exc, sqlite3.OperationalError):
        return None
    text = str(exc).lower()
    for needle, cause, what in _UNAVAILABLE:
        if needle in text:
            return StorageUnavailable(
                cause, f"database {path}: {what} ({exc})", public=f"database {path.name}: {what} ({exc})"
            )
    return None


class SqliteEngine:
    dialect = SQLITE

    def __init__(self, path: str | Path, busy_timeout_s: float = 10.0):
        self.path = Path(path)
        self.location = str(self.path)  # what the log and the CLI name
        self.busy_timeout_s = busy_timeout_s  # sqlite3 waits this long for another process's lock before it says so
        if self.path.is_dir():
            raise StorageError(
                f"database {self.path} is a directory: --db must name a database file, e.g. {self.path / 'ripplecal.db'}"
            )
        if self.path.exists() and not os.access(self.path, os.R_OK | os.W_OK):
            raise StorageError(f"database {self.path} cannot be read and written by this user: check its permissions")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._write_lock = threading.Lock()

    @property
    def files_directory(self) -> Path:
        """Where files that belong with the database go by default (recordings): beside it."""
        return self.path.expanduser().absolute().parent

    @staticmethod
    def claim(location: str, port: int | None) -> DatabaseClaim:
        """One serve per SQLite file: a flock beside it (service/store/db_claim.py)."""
        from service.store.db_claim import DatabaseClaim

        return DatabaseClaim(location, port)

    @contextlib.contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        """A connection; a sqlite3 error that passes (lock, read-only or full filesystem) becomes
        StorageUnavailable, here and in the caller's use of the connection."""
        conn = None
        try:
            conn = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute("PRAGMA journal_mode = WAL")
            yield conn
        except sqlite3.Error as exc:
            passing = unavailable(exc, self.path)
            if passing is not None:
                raise passing from exc
            raise
        finally:
            if conn is not None:
                conn.close()

    @contextlib.contextmanager
    def _writer(self) -> Iterator[None]:
        """This process's one writer at a time, waited for no longer than SQLite waits for another process's
        lock (a writer stuck on a filesystem that hangs must not hold every other thread for good)."""
        if not self._write_lock.acquire(timeout=self.busy_timeout_s):
            raise StorageUnavailable(
                "locked",
                f"database {self.path}: another write of this service held it for {self.busy_timeout_s:g} s",
                public=f"database {self.path.name}: another write of this service held it for {self.busy_timeout_s:g} s",
            )
        try:
            yield
        finally:
            self._write_lock.release()

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._writer(), self.connect() as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                with contextlib.suppress(sqlite3.Error):  # a full disk or I/O error may have rolled it back already
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def migrate(self, available: list[Migration]) -> int:
        """Apply the numbered migrations the file has not seen; its version after."""
        try:
            return self._migrate(available)
        except sqlite3.DatabaseError as exc:
            if isinstance(exc, sqlite3.OperationalError):  # locked, read-only, ...: not one connect() maps
                raise
            # e.g. "file is not a database": a text file, another format
            raise StorageError(
                f"database {self.path} is not a database SQLite can use ({exc}): --db must name a ripplecal "
                "database or a new file"
            ) from None

    def _migrate(self, available: list[Migration]) -> int:
        with self._write_lock, self.connect() as conn:
            current = conn.execute("PRAGMA user_version").fetchone()[0]
            check_not_newer(self.location, current, available)
            # SQLite's procedure for a table rebuild (a changed CHECK): foreign keys off outside the
            # transaction, checked inside it before the commit
            conn.execute("PRAGMA foreign_keys = OFF")
            try:
                for migration in available[current:]:
                    conn.execute("BEGIN IMMEDIATE")
                    try:
                        for statement in migration.statements:
                            conn.execute(statement)
                        broken = conn.execute("PRAGMA foreign_key_check").fetchall()
                        if broken:
                            raise StorageError(f"{len(broken)} foreign key violation(s), first in table {broken[0][0]}")
                        conn.execute(f"PRAGMA user_version = {migration.number}")
                        conn.execute("COMMIT")
                    except Exception as exc:
                        conn.execute("ROLLBACK")
                        raise StorageError(f"migration {migration.name} failed: {exc}") from exc
            finally:
                conn.execute("PRAGMA foreign_keys = ON")
            version: int = conn.execute("PRAGMA user_version").fetchone()[0]
            return version

    def close(self) -> None:
        """Nothing held between calls."""
