"""Issue 8 storage: one current result per operating point, earlier attempts kept as history,
progress recounted in the result's own transaction, interlock-discarded attempts not committed.
On a real SQLite file and a real PostgreSQL server; no bench."""

from service import __version__
from service.identification import AdaptiveOptions
from service.model.operating_point import OperatingPoint
from service.store.result_rows import result_row

GRID = {"torque_nm": [1.0, 2.5], "speed_rpm": [1000.0], "udc_v": [12.0]}


# `storage` (tests/conftest.py): every test here runs on SQLite and on PostgreSQL


def _failed(op, sweep_id, discarded=False):
    row = result_row(
        op, "probe", AdaptiveOptions(), "test-bench", "t0", error="InterlockTripped: EMCY 0x3210", sweep_id=sweep_id
    )
    if discarded:
        row["detail"] = {"message": "x", "discarded": "interlock"}
    return row


def test_a_discarded_attempt_is_history_once_the_point_is_measured_again(storage):
    sweep_id = storage.create_sweep("probe", 6, GRID, {}, 2, "test-bench", __version__)
    op1, op2 = (
        OperatingPoint(torque_nm=1.0, speed_rpm=1000, udc_v=12),
        OperatingPoint(torque_nm=2.5, speed_rpm=1000, udc_v=12),
    )
    storage.insert_result(_failed(op1, sweep_id))  # an ordinary failed point: committed
    first = storage.insert_result(_failed(op2, sweep_id, discarded=True))
    s = storage.get_sweep(sweep_id)
    assert (s["done_points"], s["failed_points"]) == (1, 1)  # the discarded attempt does not count
    assert storage.committed_points(sweep_id) == {(1.0, 1000.0, 12.0)}
    second = storage.insert_result(_failed(op2, sweep_id))
    assert storage.get_result(first)["superseded_by"] == second
    current = storage.sweep_results(sweep_id)
    assert [r["id"] for r in current if r["torque_nm"] == 2.5] == [second]
    assert len(storage.sweep_result_history(sweep_id)) == 3
    s = storage.get_sweep(sweep_id)
    assert (s["done_points"], s["failed_points"]) == (2, 2)
    assert storage.committed_points(sweep_id) == {(1.0, 1000.0, 12.0), (2.5, 1000.0, 12.0)}
