"""A sweep's points outside the envelope model are stored failed and never run (SweepRunner.measure_points);
a database that cannot take such a row takes the path of a measured point's: the sweep waits for it, shown
paused with the database as the reason, and the row is written when it answers again (never a crash of the
sweep). The database fails here through a storage double (a real SQLite file behind it): the window in which
a real one would have to fail, between the sweep's start and its first row, is too short for an e2e test."""

from __future__ import annotations

import contextlib
import threading
from typing import Any, Callable, Iterator

from service import __version__
from service.model.limits import outside_envelope
from service.model.operating_point import OperatingPoint
from service.runs.events import EventBroker
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.runs.states import SweepControl
from service.runs.sweep_run import SweepRunner, stored_sweep
from service.settings import load_settings
from service.store.storage import Storage, StorageUnavailable

SETTINGS = load_settings(environ={})
GRID = Grid(torque_nm=[1.0, 2.0], speed_rpm=[2000.0, 4000.0], udc_v=[12.0])
OUTSIDE = [OperatingPoint(torque_nm=t, speed_rpm=4000.0, udc_v=12.0) for t in GRID.torque_nm]


class _Bench:
    identity = "unit:no-bench"

    def run(self, *args: Any, **kwargs: Any) -> None:
        raise AssertionError("a point outside the envelope model moved the bench")


class _Broker(EventBroker):
    def __init__(self) -> None:
        super().__init__()
        self.events: list[tuple[str, dict[str, Any]]] = []

    def publish(self, event_type: str, data: dict[str, Any]) -> None:
        self.events.append((event_type, data))


class _Host:
    """The engine as a sweep's run body sees it (RunHost), its database refusing the first result row."""

    def __init__(self, storage: Storage) -> None:
        self.storage, self.settings, self.bench, self.broker = storage, SETTINGS, _Bench(), _Broker()
        self.lock = threading.RLock()
        self.shutdown_reason = "service shut down"
        self.refusals_left = 1
        self.waits: list[str] = []

    def shutting_down(self) -> bool:
        return False

    def insert_result(self, row: dict[str, Any], recorder: object) -> int:
        if self.refusals_left:
            self.refusals_left -= 1
            raise StorageUnavailable("locked", "database is locked", public="the database is locked")
        return self.storage.insert_result(row)

    def durably(self, write: Callable[[], object], what: str, cancel: threading.Event | None = None) -> bool:
        for _ in range(3):  # the engine's wait, without its backoff
            try:
                write()
                return True
            except StorageUnavailable:
                pass
        return False

    @contextlib.contextmanager
    def waiting_for_storage(self, sweep_id: int, reason: str) -> Iterator[None]:
        self.waits.append(reason)
        yield

    def publish_sweep(self, sweep_id: int) -> None:
        pass

    def new_recorder(self) -> None:
        return None


def test_a_point_never_run_waits_for_the_database_as_a_measured_point_does(tmp_path):
    assert all(outside_envelope(op, SETTINGS) is not None for op in OUTSIDE)
    storage = Storage(str(tmp_path / "not_run.db"))
    options = parse_options("probe", {})
    sweep_id = storage.create_sweep(
        "probe", 6, GRID.model_dump(), options.model_dump(), GRID.size(), _Bench.identity, __version__
    )
    host = _Host(storage)

    in_flight = SweepRunner(host).measure_points(
        sweep_id, stored_sweep(storage, sweep_id), SweepControl(), GRID, options, list(OUTSIDE), sweep_pass=1
    )

    assert in_flight is None
    [reason] = host.waits  # the sweep waited once, with the database as the reason and the point kept
    assert "the database is locked" in reason and f"the point {OUTSIDE[0].label()} is kept" in reason, reason
    paused = [data for kind, data in host.broker.events if kind == "sweep.progress" and data["state"] == "paused"]
    assert [p["storage"]["cause"] for p in paused] == ["locked"]
    rows = storage.sweep_results(sweep_id)
    assert sorted((r["torque_nm"], r["speed_rpm"]) for r in rows) == [(1.0, 4000.0), (2.0, 4000.0)]  # each once
    assert all(r["status"] == "failed" and r["detail"]["details"]["not_run"] == "outside_envelope" for r in rows)
