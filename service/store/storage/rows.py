"""Rows in and out of the database, the same for every table: a row read as its record (every `x_json`
column decoded as `x`, service/store/records.py), a write's fields encoded into its columns, the id an
INSERT made, and the timestamps the rows carry."""

from __future__ import annotations

import json
import re
from datetime import datetime, timezone
from typing import Any

from service.store.errors import StorageError


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


# the columns that hold JSON, per table: a record names them without the suffix, decoded
# (results.detail_json -> record["detail"]); a write may give them either way (decoded is encoded here)
JSON_COLUMNS = {
    "jobs": ("request",),
    "sweeps": ("grid", "options", "refinement"),
    "results": ("options", "detail", "traces", "recording"),
    "maps": ("axes", "provenance"),
    "map_validations": ("options", "summary", "cells", "download"),
    "schedules": ("sweep",),
    "runups": ("request", "result", "recording"),
}

_IDENT = re.compile(r"^[a-z_]+$")


def check_columns(fields: dict[str, Any]) -> None:
    """Column names go into the SQL as text: only plain identifiers."""
    for key in fields:
        if not _IDENT.match(key):
            raise StorageError(f"bad column name {key!r}")


def as_record(row: Any) -> Any:
    """A row as the layers above read it (service/store/records.py): every `x_json` column decoded as `x`.
    Typed by the caller's return, its table's record (tests/unit/test_records_schema.py holds them equal)."""
    record: dict[str, Any] = {}
    for key in row.keys():
        value = row[key]
        if key.endswith("_json"):
            record[key[:-5]] = json.loads(value) if value is not None else None
        else:
            record[key] = value
    return record


def encode_columns(table: str, fields: dict[str, Any]) -> dict[str, Any]:
    """{column: value} of a write: decoded JSON fields encoded into their `x_json` columns."""
    names = JSON_COLUMNS.get(table, ())
    return {
        (f"{k}_json" if k in names else k): (json.dumps(v) if k in names and v is not None else v)
        for k, v in fields.items()
    }


def new_id(cursor: Any) -> int:
    """The id of the row an INSERT made (sqlite3's lastrowid; the PostgreSQL engine's RETURNING id)."""
    row_id: int = cursor.lastrowid
    return row_id


def one_row(cursor: Any) -> bool:
    """An UPDATE or DELETE touched exactly one row."""
    rowcount: int = cursor.rowcount
    return rowcount == 1


def insert_row(conn: Any, table: str, row: dict[str, Any]) -> int:
    """One row from a {column: value} dict, in the caller's transaction; its id."""
    row = encode_columns(table, row)
    check_columns(row)
    marks = ", ".join("?" for _ in row)
    return new_id(conn.execute(f"INSERT INTO {table} ({', '.join(row)}) VALUES ({marks})", tuple(row.values())))
