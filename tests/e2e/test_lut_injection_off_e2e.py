"""Injection off end to end (issue 27, "never worse than nothing"): a measured 2 x 2 map with one cell set
injection-off in the database (Storage.set_injection_off) goes into the emulated drive as a format_version
4 image and is validated in the drive's LUT mode (`ripplecal serve` against plant_emulator in its own
process). Every validation point in an interval that has the off cell as a corner gets no compensation
at all: its residual is its uncompensated level (0 dB within 0.5 dB: the two phasors are measured apart,
each to 1 %, some 0.1 dB); the grid points on the far torque line never touch it (the torque the drive
interpolates at is the command, exact) and keep their compensation."""

from __future__ import annotations

import pytest

from service.store.storage import Storage
from tests.support.bench_rig import served_bench
from tests.support.sweep_checks import holes

pytestmark = pytest.mark.e2e
GRID = {"torque_nm": [2.0, 3.0], "speed_rpm": [1200, 1600], "udc_v": [12]}
OFF = (2.0, 1200.0, 12.0)
# the validation points whose interval has OFF as a corner of non-zero weight, whatever the measured speed
# and U_dc jitter (below 1200 rpm the speed axis clamps to 1200): OFF itself and the midpoints around it
IN_OFF_INTERVAL = {(2.0, 1200.0), (2.5, 1200.0), (2.0, 1400.0), (2.5, 1400.0)}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with served_bench(tmp_path_factory.mktemp("injection_off"), "off.db") as (emu, _, api, db):
        yield emu, api, db


def test_a_cell_with_injection_off_gives_exactly_no_compensation_in_its_intervals(rig):
    emu, api, db = rig
    r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
    assert r.status_code == 202, r.text
    sweep = api.sweep_finished(r.json()["id"], 240)
    assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
    map_id = sweep["map_id"]
    storage = Storage(db)
    try:
        assert storage.set_injection_off(map_id, [OFF]) == 1
    finally:
        storage.close()
    m = api.get(f"/maps/{map_id}")
    assert m["injection_off_cells"] == 1
    assert [(c["torque_nm"], c["speed_rpm"], c["udc_v"]) for c in m["cells"] if c["injection_off"]] == [OFF]

    r = api.post(f"/maps/{map_id}/validate", {"force": holes(m) > 0})
    assert r.status_code == 202, r.text
    job = api.job_finished(r.json()["id"], 240)
    assert job["state"] == "done", job
    v = job["validation"]
    assert (v["download"]["format_version"], v["download"]["injection_off_cells"]) == (4, 1), v["download"]
    by_point = {(c["operating_point"]["torque_nm"], c["operating_point"]["speed_rpm"]): c for c in v["cells"]}
    assert IN_OFF_INTERVAL <= set(by_point)
    for point in IN_OFF_INTERVAL:
        c = by_point[point]
        assert c["status"] == "measured" and abs(c["suppression_db"]) <= 0.5, (point, c)
        # marked: the drive injects nothing there, so its figure is no compensation, never harm
        assert c.get("no_injection") is True, (point, c)
    assert all(not c.get("no_injection") for p, c in by_point.items() if p not in IN_OFF_INTERVAL)
    assert v["no_injection"] == len(IN_OFF_INTERVAL)
    # the far torque line (3 Nm) never touches the off cell: the drive compensates there as it did
    status = {(x["torque_nm"], x["speed_rpm"]): x["status"] for x in m["cells"]}
    far = [by_point[(3.0, n)] for n in (1200.0, 1600.0) if status[(3.0, n)] == "ok"]
    assert far and all(c["suppression_db"] >= 20.0 for c in far), far
    faults = emu.control({"status": True})["faults"]
    assert faults["drive_injection_mode"] == 0 and faults["drive_torque_nm"] == 0.0, faults
