"""Storage: the repository functions the service uses, over one of two engines chosen by the `--db`
string (service/store/engines.py): a SQLite file (the embedded default) or a PostgreSQL server (a lab).
The SQL is written once, with `?` placeholders; where the engines differ it asks the engine's dialect
(service/store/dialect.py). Numbered migrations (service/store/migrations.py); every write in one
transaction, so a failure in one operating point never touches the results of others.

One module per aggregate, each a store on the shared `Database` (database.py: the engine, connections,
transactions, the one UPDATE): tokens, jobs, sweeps, results, maps (and their validations), schedules,
benches, run-ups; rows.py reads and writes a row the same way for every table. `Storage` is all of them on one
engine: its callers keep one object and the methods' plain names (`storage.get_job`)."""

from __future__ import annotations

from service.store.errors import StorageError, StorageUnavailable
from service.store.migrations import MIGRATIONS_DIR
from service.store.storage.benches import BenchStore
from service.store.storage.jobs import JobStore
from service.store.storage.maps import MapStore
from service.store.storage.results import ResultStore
from service.store.storage.rows import now_iso
from service.store.storage.runups import RunupStore
from service.store.storage.schedules import ScheduleStore
from service.store.storage.sweeps import SweepStore
from service.store.storage.tokens import TokenStore

__all__ = ["Storage", "StorageError", "StorageUnavailable", "now_iso", "MIGRATIONS_DIR"]


class Storage(TokenStore, JobStore, SweepStore, ResultStore, MapStore, ScheduleStore, BenchStore, RunupStore):
    """Every store on one database (Database.__init__ opens and migrates it); no method of its own."""
