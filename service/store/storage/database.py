"""The database every table's store shares: one engine chosen by the `--db` string
(service/store/engines.py), its connections and transactions, its migrations, its clock, and the one
UPDATE every store's `update_*` goes through."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Iterator

from service.store.engines import open_engine
from service.store.errors import StorageUnavailable
from service.store.migrations import load_migrations
from service.store.storage.rows import check_columns, encode_columns

# tables whose every write sets updated_at, on the database's clock (the one clock of a lab: a bench PC's
# may be off): another bench's service shows their progress from it (service/runs/lab.py LabWatch)
_TRACKED = ("jobs", "sweeps")


class Database:
    def __init__(self, path: str | Path, busy_timeout_s: float = 10.0, statement_timeout_s: float | None = None):
        """`path`: a SQLite file, or a `postgresql://user@host:port/dbname` URL (service/store/engines.py).
        `busy_timeout_s`: how long a call waits for another's lock (or the server's pool) before it says so;
        `statement_timeout_s`: a server's bound on one statement (default: the engine's)."""
        self.engine = open_engine(path, busy_timeout_s, statement_timeout_s)
        self.dialect = self.engine.dialect
        self.path = self.engine.path  # the SQLite file (None on a server)
        self.location = self.engine.location  # the database as the log and the CLI name it (no password)
        try:
            self.migrate()
        except BaseException:
            self.engine.close()
            raise

    @contextlib.contextmanager
    def connect(self) -> Iterator[Any]:
        """A connection (every statement its own transaction); an error that passes (a lock, a read-only
        or full filesystem, a lost server) becomes StorageUnavailable, here and in the caller's use of it."""
        with self.engine.connect() as conn:
            yield conn

    def known_unavailable(self) -> StorageUnavailable | None:
        """Why the database's last call failed, while no call has succeeded since (None: not known to be
        away; SQLite's calls answer quickly either way): what must answer at once need not wait on it again."""
        known = getattr(self.engine, "known_unavailable", None)
        return known() if known is not None else None

    @contextlib.contextmanager
    def transaction(self) -> Iterator[Any]:
        """A connection in one transaction, committed when the block ends, rolled back if it raises."""
        with self.engine.transaction() as conn:
            yield conn

    def migrate(self) -> int:
        """Apply the migrations the database has not seen (service/store/migrations.py); its schema version."""
        return self.engine.migrate(load_migrations(self.dialect.name))

    @property
    def busy_timeout_s(self) -> float:
        """How long a call waits for another's lock before the database counts as unavailable."""
        return self.engine.busy_timeout_s

    @busy_timeout_s.setter
    def busy_timeout_s(self, value: float) -> None:
        self.engine.busy_timeout_s = value  # SQLite reads it per connection; a server's pool keeps its own

    @property
    def files_directory(self) -> Path:
        """Where files that belong with the database go by default (recordings)."""
        return self.engine.files_directory

    def close(self) -> None:
        """Let go of the engine's connections (a server's pool); nothing to do on SQLite."""
        self.engine.close()

    def database_now(self) -> str:
        """The database's clock as UTC ISO text: the lab's one clock, that updated_at and heartbeats use."""
        with self.connect() as conn:
            now: str = conn.execute(f"SELECT {self.dialect.now_text}").fetchone()[0]
            return now

    def _update_row(self, table: str, row_id: int, fields: dict[str, Any]) -> None:
        """Set `fields` (decoded JSON fields encoded) of one row in one transaction."""
        if not fields:
            return
        fields = encode_columns(table, fields)
        check_columns(fields)
        sets = ", ".join(f"{k} = ?" for k in fields)
        if table in _TRACKED and "updated_at" not in fields:
            sets += f", updated_at = {self.dialect.now_text}"
        with self.transaction() as conn:
            conn.execute(f"UPDATE {table} SET {sets} WHERE id = ?", (*fields.values(), row_id))
