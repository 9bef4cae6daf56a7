"""The store's typed records (service/store/records.py) against the migrated schema, on both engines: each
record's fields are its table's columns (an `x_json` column read as `x`), so a column a migration adds
cannot go unnoticed by the records and the type checker that reads them; every table has a record or
is named here as having none."""

from __future__ import annotations

from typing import get_type_hints

import pytest

from service.store.records import (
    JobRecord,
    MapCellRecord,
    MapRecord,
    MapSummaryRecord,
    ResultRecord,
    RunupRecord,
    ScheduleRecord,
    ScheduleRunRecord,
    SweepRecord,
    ValidationRecord,
)
from service.store.storage import Storage
from tests.unit.test_migrations import _postgres_columns, _sqlite_columns

# record -> (its table, the fields a query joins in from elsewhere: not the table's columns)
WHOLE_ROWS = {
    JobRecord: ("jobs", set()),
    SweepRecord: ("sweeps", set()),
    ResultRecord: ("results", set()),
    MapRecord: ("maps", {"cells"}),  # map_cells joined with results (MapCellRecord)
    ValidationRecord: ("map_validations", set()),
    RunupRecord: ("runups", set()),
    ScheduleRecord: ("schedules", set()),
    ScheduleRunRecord: ("schedule_runs", {"sweep_state"}),  # its sweep's state
}
# tables the layers above read through no record of their own (Storage hands out plain dicts or values)
NO_RECORD = {"api_tokens", "benches", "map_cells", "schema_version"}


def _decoded_columns(db_location: str) -> dict[str, set[str]]:
    """Each table's columns as Storage reads them (service/store/storage/rows.py as_record: `x_json` as `x`)."""
    Storage(db_location).close()  # migrated to the newest schema
    if db_location.startswith("postgresql://"):
        columns = _postgres_columns(db_location)
    else:
        columns = _sqlite_columns(db_location)
    return {table: {c.removesuffix("_json") for c in names} for table, names in columns.items()}


def _fields(record: type) -> set[str]:
    return set(get_type_hints(record))


@pytest.mark.parametrize("record", list(WHOLE_ROWS), ids=lambda r: r.__name__)
def test_each_record_has_exactly_its_tables_columns(db_location, record):  # on each engine (tests/conftest.py)
    table, joined = WHOLE_ROWS[record]
    columns = _decoded_columns(db_location)[table]
    fields = _fields(record)
    assert fields - joined == columns, (
        f"{record.__name__} (service/store/records.py) and table {table}: columns without a field "
        f"{sorted(columns - fields)}, fields without a column {sorted(fields - joined - columns)}; "
        "add the field a migration added (or drop the one it removed)"
    )


def test_the_partial_records_read_only_columns_that_exist(db_location):
    columns = _decoded_columns(db_location)
    assert _fields(MapSummaryRecord) <= columns["maps"]
    # a map cell: its map_cells row (less the map's id) with its result's columns (Storage.get_map)
    cell = _fields(MapCellRecord)
    assert columns["map_cells"] - {"map_id"} <= cell
    assert cell <= columns["map_cells"] | columns["results"]


def test_every_table_has_a_record_or_is_named_as_having_none(db_location):
    tables = set(_decoded_columns(db_location)) - {"schema_version"}
    with_record = {table for table, _ in WHOLE_ROWS.values()}
    assert tables == (with_record | NO_RECORD) - {"schema_version"}, (
        "a table without a record: add its TypedDict to service/store/records.py and to WHOLE_ROWS here, "
        "or name it in NO_RECORD"
    )
