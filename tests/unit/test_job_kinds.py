"""Job kinds as a registry (service/runs/kinds): every kind a job can name is one module in it, the engine
runs a job through whatever the registry holds for its kind (no list of kinds of its own), and a sweep's
grid is planned once: the plan made at submit travels with the sweep and is not made again."""

from __future__ import annotations

import pytest

from service.runs import kinds as kinds_package
from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.runs.identify import parse_options
from service.runs.kinds import KINDS, JobKind, kind_of
from service.runs.kinds import sweep as sweep_kind
from service.runs.plans import Grid, RegimePlacement, SweepPlan, plan_grid
from service.runs.sweep_run import stored_plan
from service.settings import load_settings
from service.store.storage import Storage
from tests.support.waiting import wait_run_finished

SETTINGS = load_settings(environ={})
EXAMPLE = Grid(torque_nm=[1, 2, 3, 4], speed_rpm=[1000, 1400, 1800, 2200, 2600], udc_v=[12])
AROUND = RegimePlacement(speeds_around_onset=True, spacing_rpm=100)


class _Bench:
    identity = "unit:no-bench"

    def check_reachable(self) -> None:  # a bench that was reached at start
        pass


def test_every_kind_a_job_can_name_is_one_module_in_the_registry(tmp_path):
    assert set(KINDS) == {"identification", "sweep", "validation", "refinement", "runup"}
    storage = Storage(tmp_path / "kinds.db")  # the schema's jobs.kind CHECK allows every kind of the registry
    try:
        for name in KINDS:
            storage.create_job(name, {})
    finally:
        storage.close()
    for name, kind in KINDS.items():
        assert kind.name == name and callable(kind.submit) and callable(kind.check_here) and callable(kind.run)
        assert kind.run.__module__ == f"{kinds_package.__name__}.{name}"
    assert kind_of(None) is KINDS["sweep"]  # a sweep stored before kinds were named runs as a sweep


def test_a_sweep_submitted_with_its_plan_is_not_planned_again(tmp_path, monkeypatch):
    storage = Storage(str(tmp_path / "kinds.db"))
    engine = Engine(storage, _Bench(), SETTINGS, EventBroker())  # never started: the sweep stays queued
    options = parse_options("probe", {"override_envelope_model": True})
    planned = plan_grid(EXAMPLE, AROUND, SETTINGS)  # the one plan (POST /sweeps makes it to check the size)

    def planned_again(*args, **kwargs):
        raise AssertionError("the sweep's grid was planned a second time")

    monkeypatch.setattr(sweep_kind, "plan_grid", planned_again)
    sweep = storage.get_sweep(engine.submit_sweep(EXAMPLE, "probe", options, regime=AROUND, planned=planned))
    assert Grid.model_validate(sweep["grid"]) == planned.grid != EXAMPLE
    # the run reads the stored plan: the planned grid's points, in the one order
    assert stored_plan(sweep).points == SweepPlan.from_grid(planned.grid).points
    assert sweep["total_points"] == len(stored_plan(sweep).points)


def test_the_engine_runs_a_job_through_what_the_registry_holds_for_its_kind(tmp_path, monkeypatch):
    storage = Storage(str(tmp_path / "kinds.db"))
    ran: list[tuple[str, dict]] = []

    def submit(host, note: str, bench: str | None = None) -> int:
        job_id = host.create_job("validation", {"note": note}, bench=bench)
        host.publish_job(job_id)
        return job_id

    def check_here(host, job: dict) -> None:
        ran.append(("check_here", job["request"]))

    def run(host, job_id: int, job: dict) -> None:
        ran.append(("run", job["request"]))

    monkeypatch.setitem(KINDS, "validation", JobKind("validation", submit=submit, check_here=check_here, run=run))
    engine = Engine(storage, _Bench(), SETTINGS, EventBroker())
    engine.start()
    try:
        job_id = engine.submit("validation", "from the registry")
        job = wait_run_finished(lambda: storage.get_job(job_id), timeout_s=60, what=f"job {job_id}")
    finally:
        engine.stop(timeout_s=30)
    assert job["state"] == "done", job
    assert ran == [("check_here", {"note": "from the registry"}), ("run", {"note": "from the registry"})]


def test_an_unknown_kind_is_refused_at_submit(tmp_path):
    engine = Engine(Storage(str(tmp_path / "kinds.db")), _Bench(), SETTINGS, EventBroker())
    with pytest.raises(KeyError):
        engine.submit("run_up")
