"""The run engine on the emulated bench: cancel leaves the bench safe, pause/resume, a failing
point is stored as failed and the sweep goes on, corrupted DAQ bytes are discarded and re-measured.
The service layer runs in this process; plant_emulator is its own process."""

import time

import pytest

from service.bench.measurement import MeasurementError
from service.calibration_service import CalibrationService
from service.runs.identify import parse_options
from service.runs.plans import Grid
from service.settings import load_settings
from tests.support.bench_rig import emulator_control
from tests.support.operating_points import OP1_POINT
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    settings = load_settings(
        environ={},
        overrides={"emulator.speedup": 0.0, "server.db_path": str(tmp_path_factory.mktemp("engine") / "e.db")},
    )
    with CalibrationService(settings) as service:
        yield service


def wait_for(predicate, timeout_s=120.0):
    return wait_until(predicate, timeout_s)


def bench_is_safe(svc) -> bool:
    drive = svc.bench.drive.read_status()
    load = svc.bench.load.read_status()
    return drive.state.value != "operation_enabled" and load.state.value != "operation_enabled" and not svc.bench.busy


def test_cancel_during_a_grid_search_leaves_the_bench_safe(svc):
    written = svc.bench.setpoints_written()
    job_id = svc.engine.submit_identification(OP1_POINT, "grid", parse_options("grid", {}))
    wait_for(lambda: svc.storage.get_job(job_id)["state"] == "running")
    # well inside the 360 points: some of them measured (each point is one theta setpoint)
    wait_for(lambda: svc.bench.setpoints_written() >= written + 10)
    svc.engine.cancel_job(job_id)
    job = wait_for(lambda: (j := svc.storage.get_job(job_id))["state"] in ("cancelled", "done", "failed") and j, 30)
    assert job["state"] == "cancelled"
    assert wait_for(lambda: bench_is_safe(svc), 10)
    # the bench works on after a cancel
    job_id = svc.engine.submit_identification(OP1_POINT, "probe", parse_options("probe", {}))
    job = wait_for(lambda: (j := svc.storage.get_job(job_id))["state"] in ("done", "failed") and j)
    assert job["state"] == "done"


def test_pause_resume_and_a_failing_point(svc):
    # the DAQ stream corrupted while the sweep is paused: every window of the next point is refused
    # (docs/interfaces.md, DAQ stream frame), that point fails with its reason, the sweep goes on and builds its map
    ep = svc.emulator.endpoints  # the service's emulator child (its control socket)
    grid = Grid(torque_nm=[2.5], speed_rpm=[1500, 2000, 2300], udc_v=[12])
    sweep_id = svc.engine.submit_sweep(grid, "probe", parse_options("probe", {}))
    wait_for(lambda: svc.storage.get_sweep(sweep_id)["done_points"] >= 1)
    svc.engine.control_sweep(sweep_id, "pause")
    wait_for(lambda: svc.storage.get_sweep(sweep_id)["state"] == "paused")
    held = svc.storage.get_sweep(sweep_id)["done_points"]
    # the pause has taken effect: the run ended (bench safe) and the sweep's job is parked, queued but
    # out of the worker's queue
    sweep_job = next(j for j in svc.storage.list_jobs() if j["sweep_id"] == sweep_id)
    wait_for(lambda: bench_is_safe(svc) and svc.storage.get_job(sweep_job["id"])["state"] == "queued", 60)
    assert svc.storage.get_sweep(sweep_id)["done_points"] == held  # nothing runs while paused
    assert emulator_control(ep, {"fault": "daq_corrupt", "rate": 1e-3})["ok"]
    try:
        svc.engine.resume_sweep(sweep_id)
        wait_for(lambda: svc.storage.get_sweep(sweep_id)["done_points"] > held)
    finally:
        assert emulator_control(ep, {"fault": "clear"})["ok"]
    sweep = wait_for(lambda: (s := svc.storage.get_sweep(sweep_id))["state"] in ("done", "failed") and s)
    assert sweep["state"] == "done" and sweep["done_points"] == 3
    history = svc.storage.sweep_result_history(sweep_id)
    failed = [r for r in history if r["status"] == "failed"]
    # the bad frames spoil the windows (or, before them, the settling): the reason names them
    assert failed and all("DAQ gap" in r["error"] for r in failed), [r["error"] for r in failed]
    # the sweep's second pass measured each failed point once more, with the stream clean again
    current = {r["speed_rpm"]: r for r in svc.storage.sweep_results(sweep_id)}
    for r in failed:
        again = current[r["speed_rpm"]]
        assert r["superseded_by"] == again["id"] and again["detail"]["details"]["sweep_pass"] == 2
    assert current[1500.0]["status"] == "ok" and current[1500.0]["suppression_db"] >= 40
    assert sweep["map_id"] is not None
    assert bench_is_safe(svc)


def test_a_paused_sweep_releases_the_bench_and_resume_queues_it_again(svc):
    """While a sweep waits paused, an identification runs; resume queues the sweep, which measures its
    remaining points from a settled state and ends done."""
    grid = Grid(torque_nm=[1.5, 2.5], speed_rpm=[1500, 2000], udc_v=[12])
    sweep_id = svc.engine.submit_sweep(grid, "probe", parse_options("probe", {}))
    wait_for(lambda: svc.storage.get_sweep(sweep_id)["done_points"] >= 1)
    svc.engine.control_sweep(sweep_id, "pause")

    def sweep_job() -> dict:
        return next(j for j in svc.storage.list_jobs() if j["sweep_id"] == sweep_id)

    # parked: the sweep paused, the bench free, its job queued again but out of the worker's hands (the
    # sweep's state is written before its job's: wait for both)
    wait_for(
        lambda: (
            svc.storage.get_sweep(sweep_id)["state"] == "paused"
            and not svc.bench.busy
            and sweep_job()["state"] == "queued"
        )
    )
    assert not svc.storage.bench_busy(svc.settings.bench_name)  # a schedule firing now would start at once
    held = svc.storage.get_sweep(sweep_id)["done_points"]
    job_id = svc.engine.submit_identification(OP1_POINT, "probe", parse_options("probe", {}))
    job = wait_for(lambda: (j := svc.storage.get_job(job_id))["state"] in ("done", "failed") and j)
    assert job["state"] == "done", job
    sweep = svc.storage.get_sweep(sweep_id)
    assert sweep["state"] == "paused" and sweep["done_points"] == held  # untouched meanwhile
    svc.engine.resume_sweep(sweep_id)
    sweep = wait_for(lambda: (s := svc.storage.get_sweep(sweep_id))["state"] in ("done", "failed") and s)
    assert sweep["state"] == "done" and sweep["done_points"] == 4 and sweep["map_id"] is not None
    # the same job, resumed (it ends just after its sweep)
    wait_for(lambda: sweep_job()["state"] == "done")
    assert bench_is_safe(svc)


def test_a_paused_sweep_cancelled_ends_with_what_it_measured(svc):
    grid = Grid(torque_nm=[1.5, 2.5], speed_rpm=[1500, 2000], udc_v=[12])
    sweep_id = svc.engine.submit_sweep(grid, "probe", parse_options("probe", {}))
    wait_for(lambda: svc.storage.get_sweep(sweep_id)["done_points"] >= 1)
    svc.engine.control_sweep(sweep_id, "pause")
    wait_for(lambda: svc.storage.get_sweep(sweep_id)["state"] == "paused" and not svc.bench.busy)
    svc.engine.control_sweep(sweep_id, "cancel")
    sweep = svc.storage.get_sweep(sweep_id)
    assert sweep["state"] == "cancelled" and sweep["map_id"] is not None
    assert next(j for j in svc.storage.list_jobs() if j["sweep_id"] == sweep_id)["state"] == "cancelled"
    # the map says it is partial (issue 30: a cancelled sweep's map looked whole), and its CSV says so too
    from service.maps.lut_export import export_map
    from service.maps.view import map_view

    m = map_view(svc.storage, sweep["map_id"])
    assert m is not None and m.partial is not None and "cancelled after" in m.partial, m
    assert f"of {sweep['total_points']} points" in m.partial
    assert "# PARTIAL: " in export_map(m.model_dump(), "csv")


def test_corrupted_windows_are_refused_then_measured_again(svc):
    """A window that holds a bad frame or a gap is discarded and measured again (docs/interfaces.md,
    DAQ stream frame)."""
    ep = svc.emulator.endpoints  # the service's emulator child (its control socket)
    before = svc.bench.daq.counters
    with svc.bench.operating_point(OP1_POINT, 6) as session:
        session.apply_theta(0.0, 0.0)
        clean = session.measure(36).phasor
        assert emulator_control(ep, {"fault": "daq_corrupt", "rate": 1e-3})["ok"]  # every window gets bad frames
        try:
            session.apply_theta(0.001, 0.0)
            with pytest.raises(MeasurementError, match="DAQ gap or bad frame"):
                session.measure(36)
        finally:
            assert emulator_control(ep, {"fault": "clear"})["ok"]
        session.apply_theta(0.0, 0.0)  # its sync toggle lies beyond the corrupted data
        again = session.measure(36).phasor
        assert session.windows_discarded >= 5
    assert abs(again.complex - clean.complex) < 0.02 * abs(clean.complex)
    assert svc.bench.daq.counters.crc_failures > before.crc_failures
    assert bench_is_safe(svc)


def test_identification_succeeds_through_occasional_bad_frames(svc):
    ep = svc.emulator.endpoints  # the service's emulator child (its control socket)
    assert emulator_control(ep, {"fault": "daq_corrupt", "rate": 5e-6})["ok"]  # about 1 bad frame in 17000
    try:
        job_id = svc.engine.submit_identification(OP1_POINT, "probe", parse_options("probe", {}))
        job = wait_for(lambda: (j := svc.storage.get_job(job_id))["state"] in ("done", "failed") and j)
    finally:
        assert emulator_control(ep, {"fault": "clear"})["ok"]
    assert job["state"] == "done", job
    assert svc.storage.get_result(job["result_id"])["suppression_db"] >= 40


def test_the_lut_objects_are_read_when_idle_never_during_a_run(svc):
    """/bench/status reads the LUT the drive holds (0x2001:2-4) in idle rounds only: during a run the
    drive's SDO channel is the run's, and the LUT changes only by a download."""
    calls = []
    original = svc.bench.drive.lut_in_force

    def counted():
        calls.append(time.monotonic())
        return original()

    svc.bench.drive.lut_in_force = counted
    try:
        with svc.bench.operating_point(OP1_POINT, 6) as session:
            before = len(calls)
            session.apply_theta(0.0, 0.0)
            for _ in range(3):
                svc.bench.refresh_status()
                session.measure(12)
            during = len(calls) - before
        after_run = len(calls)
        # read again once idle (by this refresh or the status poller's, whichever holds the bench)
        wait_until(
            lambda: svc.bench.refresh_status() and len(calls) > after_run,
            timeout_s=30,
            what="the LUT objects read in an idle status round",
        )
    finally:
        svc.bench.drive.lut_in_force = original
    assert during == 0
    assert bench_is_safe(svc)


def test_each_sweep_point_starts_from_the_neighbour_measured_before_it_in_the_same_run(svc):
    """Priors are read from the store once a run and each stored point added as the store gives it back
    (SweepRunner.measure_points): a point's prior is the nearest ok result measured before it in the sweep."""
    grid = Grid(torque_nm=[2.0], speed_rpm=[1200, 1300, 1400, 1500], udc_v=[12])
    sweep_id = svc.engine.submit_sweep(grid, "probe", parse_options("probe", {}))
    sweep = wait_for(lambda: (s := svc.storage.get_sweep(sweep_id))["state"] in ("done", "failed") and s, 300)
    assert sweep["state"] == "done"
    rows = sorted(svc.storage.sweep_results(sweep_id), key=lambda r: r["id"])  # in measuring order
    assert [r["status"] for r in rows] == ["ok"] * 4
    assert rows[0]["detail"]["details"]["prior"] is None  # nothing measured before it
    for before, r in zip(rows, rows[1:]):
        assert r["detail"]["details"]["prior"].startswith(f"neighbour 2 Nm / {before['speed_rpm']:g} rpm"), r
