"""Storage's SQL is written once with `?`; the PostgreSQL engine turns it into psycopg's `%s` without
touching literals, and the dialect's JSON expressions read and write alike on both engines."""

from __future__ import annotations

import pytest

from service.model.operating_point import OperatingPoint
from service.store.dialect import format_placeholders
from service.store.result_rows import result_row


@pytest.mark.parametrize(
    "sql, expected",
    [
        ("SELECT * FROM jobs WHERE id = ? AND state = ?", "SELECT * FROM jobs WHERE id = %s AND state = %s"),
        ("SELECT '?' AS q, x FROM t WHERE y = ?", "SELECT '?' AS q, x FROM t WHERE y = %s"),
        ("SELECT 'it''s ?' FROM t WHERE y = ?", "SELECT 'it''s ?' FROM t WHERE y = %s"),
        (
            "SELECT printf('%.1f', x) FROM t WHERE name LIKE 'a%'",
            "SELECT printf('%%.1f', x) FROM t WHERE name LIKE 'a%%'",
        ),
        ('SELECT "odd?name" FROM t WHERE a = ?', 'SELECT "odd?name" FROM t WHERE a = %s'),
    ],
)
def test_placeholders_become_psycopgs_outside_literals(sql, expected):
    assert format_placeholders(sql) == expected


def test_json_expressions_read_and_write_alike(storage):  # on each engine (tests/conftest.py)
    text = storage.dialect.json_text("recording_json", "deleted")
    sweep_id = storage.create_sweep("probe", 6, {}, {}, 1, "b", "v")
    op = OperatingPoint(torque_nm=1.0, speed_rpm=1000.0, udc_v=12.0)
    rid = storage.insert_result(result_row(op, "probe", None, "b", "t0", error="x", sweep_id=sweep_id))
    storage.set_result_recording(rid, {"format": "mf4", "bytes": 3})
    with storage.connect() as conn:
        assert conn.execute(f"SELECT {text} FROM results WHERE id = ?", (rid,)).fetchone()[0] is None
    storage.mark_recordings_deleted([rid], "retention")
    assert storage.get_result(rid)["recording"] == {"format": "mf4", "bytes": 3, "deleted": "retention"}
    with storage.connect() as conn:
        assert conn.execute(f"SELECT {text} FROM results WHERE id = ?", (rid,)).fetchone()[0] == "retention"
    assert storage.committed_points(sweep_id) == {(1.0, 1000.0, 12.0)}
