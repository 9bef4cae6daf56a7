"""The numbered schema migrations, the same numbers on every engine.

migrations/NNNN_name.sql holds SQL both engines run as it is; where they differ (SQLite's table
rebuilds for a changed CHECK, its INTEGER PRIMARY KEY ids, REAL) migrations/sqlite/NNNN_name.sql and
migrations/postgresql/NNNN_name.sql hold one file per engine instead."""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

from service.store.errors import StorageError

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"
ENGINES = ("sqlite", "postgresql")
_MIGRATION_NAME = re.compile(r"^(\d{4})_[a-z0-9_]+\.sql$")


class Migration(NamedTuple):
    number: int
    name: str  # its file name
    statements: list[str]


def _numbered(directory: Path) -> dict[int, Path]:
    found: dict[int, Path] = {}
    for path in sorted(directory.glob("*.sql")):
        m = _MIGRATION_NAME.match(path.name)
        if not m:
            raise StorageError(f"migration file {path.name} is not named NNNN_description.sql")
        found[int(m.group(1))] = path
    return found


def migration_files(engine: str = "sqlite", directory: Path = MIGRATIONS_DIR) -> list[tuple[int, Path]]:
    """[(number, file)] the engine runs, in order: the common file, else the engine's own. A number
    must have one common file or one file for every engine."""
    common = _numbered(directory)
    own = {name: _numbered(directory / name) for name in ENGINES}
    numbers = sorted(set(common).union(*own.values()))
    if numbers != list(range(1, len(numbers) + 1)):
        raise StorageError(f"migrations must be numbered 1..N without gaps, found {numbers}")
    chosen = []
    for n in numbers:
        engines_with_own = [name for name in ENGINES if n in own[name]]
        if n in common and engines_with_own:
            raise StorageError(f"migration {n:04d} is both common and for {', '.join(engines_with_own)}")
        if n not in common and len(engines_with_own) != len(ENGINES):
            missing = sorted(set(ENGINES) - set(engines_with_own))
            raise StorageError(f"migration {n:04d} has no file for {', '.join(missing)}")
        chosen.append((n, common[n] if n in common else own[engine][n]))
    return chosen


def check_not_newer(location: str, current: int, available: list[Migration]) -> None:
    """StorageError if the database's schema is newer than this software's migrations (a newer ripplecal
    wrote it): nothing is touched."""
    if current > len(available):
        raise StorageError(f"database {location} is at schema {current}, newer than this software ({len(available)})")


def load_migrations(engine: str = "sqlite", directory: Path = MIGRATIONS_DIR) -> list[Migration]:
    return [Migration(n, path.name, split_sql(path.read_text())) for n, path in migration_files(engine, directory)]


def split_sql(script: str) -> list[str]:
    """Statements of a migration script (no semicolons inside our literals; comments stripped)."""
    lines = [line.split("--", 1)[0] for line in script.splitlines()]
    return [stmt.strip() for stmt in "\n".join(lines).split(";") if stmt.strip()]
