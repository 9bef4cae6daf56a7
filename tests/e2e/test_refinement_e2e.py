"""A map refined on the drive (POST /maps/{id}/refine), end to end: the emulated bench in its own process,
`ripplecal serve --bench` pointed at it, a real SQLite file shared by restarts. The refinement is a
sweep of kind `refinement`: it is cancelled and resumed after a crash as any sweep is, and measures each
of its cells once. Assertions are on states, counts and provenance, never on how well a round did (the
figures are `make bench`'s)."""

from __future__ import annotations

import os
import signal

import pytest

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.service_process import ServiceProcess, cli
from tests.support.sweep_checks import results_per_point

pytestmark = pytest.mark.e2e
# across the field-weakening turn: the midpoints at 2200 rpm miss 30 dB, so a round has work to do
GRID = {"torque_nm": [2.0, 3.0], "speed_rpm": [1800, 2600], "udc_v": [12]}


@pytest.fixture(scope="module")
def emu():
    rig = EmulatorRig()
    yield rig
    rig.stop()


def start(emu: EmulatorRig, db) -> tuple[ServiceProcess, Api]:
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(db.parent)))
    svc.wait_ready()
    api = Api(svc, db)
    assert api.post("/bench/fault-reset").status_code == 200  # whatever an earlier test left
    return svc, api


def swept_map(api: Api) -> int:
    r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
    assert r.status_code == 202, r.text
    sweep = api.sweep_finished(r.json()["id"], 300)
    assert sweep["state"] == "done", sweep
    return sweep["map_id"]


def refinement_result(api: Api, source: int, body: dict, timeout_s: float) -> dict:
    """POST /maps/{source}/refine with `body`, waited for: the job's result, once it is done."""
    r = api.post(f"/maps/{source}/refine", body)
    assert r.status_code == 202, r.text
    job = api.job_finished(r.json()["id"], timeout_s)
    assert job["state"] == "done", job
    return job["result"]


def test_a_refinement_validates_inserts_identifies_and_names_the_refined_map(emu, tmp_path):
    db = tmp_path / "refine.db"
    svc, api = start(emu, db)
    try:
        source = swept_map(api)
        r = api.post(f"/maps/{source}/refine", {"target_db": 30, "max_cells": 4})
        assert r.status_code == 202 and r.json()["kind"] == "refinement", r.text
        job = api.job_finished(r.json()["id"], 600)
        assert job["state"] == "done", job
        result = job["result"]
        assert result["source_map_id"] == source and result["rounds"] and result["cells_added"] <= 4
        assert result["holds"] or result["stopped"]  # every point held, or it says why not
        assert result["rounds"][0]["map_id"] == source and result["rounds"][0]["points"] == 9
        refined = api.get(f"/maps/{result['map_id']}")
        if result["cells_added"]:
            # the refined map keeps its provenance; its axes hold what the rounds inserted
            assert (
                refined["refined_from"] == source and refined["provenance"]["refinement_id"] == result["refinement_id"]
            )
            for rnd in result["rounds"][:-1]:
                for axis, values in rnd["inserted"].items():
                    assert set(values) <= set(refined["axes"][axis])
            assert (
                refined["axes"]["speed_rpm"] != GRID["speed_rpm"] or refined["axes"]["torque_nm"] != GRID["torque_nm"]
            )
        # its validation is the refinement's final one, in LUT mode, at every grid point and midpoint
        validation = api.get(f"/maps/{result['map_id']}/validation")
        assert validation["id"] == result["validation"]["id"]
        n_t, n_n = len(refined["axes"]["torque_nm"]), len(refined["axes"]["speed_rpm"])
        assert len(validation["cells"]) == (2 * n_t - 1) * (2 * n_n - 1)
        # a later round measures again only where the drive's injection changed (the source's grid points whose
        # cells stayed keep theirs): the rest is taken from the round before, at no plant time
        reused = [c for c in validation["cells"] if c.get("reused")]
        assert validation["items_reused"] == len(reused) and all(c["plant_time_s"] == 0.0 for c in reused)
        assert len(result["rounds"]) < 2 or reused, result["rounds"]
        sweep = api.get(f"/sweeps/{result['refinement_id']}")
        assert sweep["kind"] == "refinement" and sweep["state"] == "done" and sweep["map_id"] == result["map_id"]
        # listed and counted as what it is (issue 30): the map it refines; done = total in cells, whatever
        # the rounds measured again; a verdict that reads in one line, the details apart
        listed = {s["id"]: s for s in api.get("/sweeps")}[result["refinement_id"]]
        assert listed["kind"] == "refinement" and listed["source_map_id"] == source, listed
        assert listed["progress"]["done"] == listed["progress"]["total"], listed["progress"]
        assert result["stopped"] is None or len(result["stopped"]) <= 300, result["stopped"]
        listed = cli("sweeps", "list", "--db", str(db)).stdout
        assert f"refinement of map {source}" in next(
            line for line in listed.splitlines() if line.split()[:1] == [str(result["refinement_id"])]
        ), listed
        shown = cli("sweeps", "show", str(result["refinement_id"]), "--db", str(db)).stdout
        assert shown.startswith(f"refinement {result['refinement_id']} of map {source}: done"), shown
        # each cell the refinement identified, once
        assert set(results_per_point(db, result["refinement_id"]).values()) <= {1}
        assert not api.get("/bench/status")["busy"]
        api.close()
    finally:
        svc.stop()


def test_a_refinement_is_cancelled_and_resumed_after_a_crash_as_a_sweep(emu, tmp_path):
    db = tmp_path / "crash.db"
    svc, api = start(emu, db)
    try:
        source = swept_map(api)
        # cancel: the refinement (a sweep of kind refinement) ends cancelled, the bench safe
        job_id = api.post(f"/maps/{source}/refine", {"max_cells": 4}).json()["id"]
        sweep_id = api.get(f"/jobs/{job_id}")["sweep_id"]
        api.wait(lambda: api.get(f"/sweeps/{sweep_id}")["state"] == "running", 60, "refinement running")
        # the lab lists what the bench runs as what it is (issue 30), not as a sweep
        api.wait(
            lambda: f"refinement {sweep_id}" in [b["running"] for b in api.get("/benches")], 30, "the lab's running"
        )
        assert api.post(f"/sweeps/{sweep_id}/cancel").status_code == 200
        assert api.job_finished(job_id, 300)["state"] == "cancelled"
        assert api.get(f"/sweeps/{sweep_id}")["state"] == "cancelled" and not api.get("/bench/status")["busy"]

        # kill -9 during a round: after the restart the refinement is interrupted, resumes from its step
        job_id = api.post(f"/maps/{source}/refine", {"max_cells": 4}).json()["id"]
        sweep_id = api.get(f"/jobs/{job_id}")["sweep_id"]
        api.wait(
            lambda: (
                (s := api.get(f"/sweeps/{sweep_id}"))["refinement"]["phase"] == "measure"
                or s["state"] not in ("queued", "running")
            ),
            300,
            "a round measuring its cells",
        )
        api.close()
    finally:
        os.killpg(svc.proc.pid, signal.SIGKILL)
        svc.proc.wait(20)
        svc.log.close()
    svc, api = start(emu, db)
    try:
        sweep = api.get(f"/sweeps/{sweep_id}")
        if sweep["state"] == "interrupted":
            assert api.post(f"/sweeps/{sweep_id}/resume").status_code == 200
        sweep = api.wait(
            lambda: (s := api.get(f"/sweeps/{sweep_id}"))["state"] in ("done", "failed", "cancelled") and s,
            600,
            "refinement finished after the restart",
        )
        assert sweep["state"] == "done", sweep
        refinement = sweep["refinement"]
        assert refinement["phase"] == "done" and (refinement["holds"] or refinement["stopped"])
        # no cell identified twice across the crash
        assert set(results_per_point(db, sweep_id).values()) <= {1}
        assert refinement["cells_added"] == sum(results_per_point(db, sweep_id).values())
        api.close()
    finally:
        svc.stop()


@pytest.mark.parametrize(("lut_cells", "interpolation"), [("int11", None), ("int11-sparse", "cartesian")])
def test_a_refinement_places_breakpoints_from_curves_before_it_validates(emu, tmp_path, lut_cells, interpolation):
    """placement curves (service/maps/placement.py): lines of candidate cells identified at the midpoints, kept
    where the drive's interpolation of their neighbours misses, bisected again; then one map, validated, its LUT
    in int11 cells (image version 6), or int11-sparse (version 7: per-row speed breakpoints). Placed and validated
    in a refinement's default interpolation (cubic; an int11-sparse LUT the drive's default, cubic is never sparse),
    or in the one the validation names: the refined map records it, and its validation's download (which names none)
    puts it in the drive, as every later download and export would."""
    db = tmp_path / "curves.db"
    svc, api = start(emu, db)
    try:
        source = swept_map(api)
        body = {"target_db": 30, "max_cells": 24, "placement": "curves", "lut_cells": lut_cells}
        if interpolation is not None:
            body["validation"] = {"interpolation": interpolation}
        result = refinement_result(api, source, body, 900)
        placement = result["placement"]
        # round one: the midpoint of each axis' one interval, a line of cells each (2 + 2 + their cross cell)
        assert placement and placement[0]["candidates"] == {"torque_nm": 1, "speed_rpm": 1}
        refined = api.get(f"/maps/{result['map_id']}")
        kept = {a: sorted({v for p in placement for v in p["inserted"].get(a, [])}) for a in ("torque_nm", "speed_rpm")}
        for axis, values in kept.items():
            assert set(values) <= set(refined["axes"][axis])
        # the turn lies between 1800 and 2600 rpm: the interpolation misses it, so speed values were kept
        assert kept["speed_rpm"], placement
        receipt = api.get(f"/maps/{result['map_id']}/validation")["download"]
        n_values = sum(len(v) for v in refined["axes"].values())
        n_cells = len(refined["axes"]["torque_nm"]) * len(refined["axes"]["speed_rpm"])
        if lut_cells == "int11":
            assert placement[-1]["bytes"] == result["rounds"][0]["bytes"]
            # int11 cells: the drive took a version 6 image of 3 bytes a cell (28 + 4 per axis value), CRC read back
            assert receipt["format_version"] == 6 and receipt["bytes"] == 28 + 4 * n_values + 3 * n_cells, receipt
        else:
            # version 7: a bit a cell and 3 bytes a stored cell; at least the rows' ends stored, at most every cell
            n_rows = len(refined["axes"]["torque_nm"])
            least, most = (28 + 4 * n_values + (n_cells + 7) // 8 + 3 * k for k in (2 * n_rows, n_cells))
            assert receipt["format_version"] == 7 and least <= receipt["bytes"] <= most, receipt
            final_round = [r for r in result["rounds"] if r["map_id"] == result["map_id"]]
            assert final_round and final_round[-1]["bytes"] == receipt["bytes"], (result["rounds"], receipt)
        assert refined["provenance"]["lut_cells"] == lut_cells
        assert refined["provenance"]["interpolation"] == receipt["interpolation"] == (interpolation or "cubic")
        # the first validation judges the placed map, every identified cell once, all within the budget
        assert result["rounds"][0]["map_id"] != source and result["cells_added"] <= 24
        assert set(results_per_point(db, result["refinement_id"]).values()) <= {1}
        assert not api.get("/bench/status")["busy"]
        api.close()
    finally:
        svc.stop()


def test_a_refinement_inserts_nothing_its_bench_time_budget_cannot_validate(emu, tmp_path):
    """max_bench_s spent ahead (service/runs/refinement.py BenchBudget): the first placement round's lines are
    measured, but a 3 x 3 grid's validation alone (25 points) would cost more than the 3 s budget, so no value is
    inserted, each left out with the budget as its reason; the map as it is is validated once, and no round follows
    it but the guard's (the verdict names the budget where points still fail)."""
    db = tmp_path / "budget.db"
    svc, api = start(emu, db)
    try:
        source = swept_map(api)
        body = {"target_db": 30, "max_cells": 24, "placement": "curves", "lut_cells": "int11", "max_bench_s": 3.0}
        result = refinement_result(api, source, body, 600)
        placement = result["placement"]
        assert placement and not any(placement[0]["inserted"].values()), placement
        assert placement[0]["left_out"] and all("bench time budget" in why for why in placement[0]["left_out"])
        assert api.get(f"/maps/{result['map_id']}")["axes"] == api.get(f"/maps/{source}")["axes"]
        # one validation; after it only the guard, which never waits on a budget (never worse than no compensation)
        rounds = result["rounds"]
        assert len(rounds) == 1 or (len(rounds) == 2 and rounds[1]["injection_off"] > 0), rounds
        # what a stepped point of that validation cost (the budget's next prediction): its settling and two windows
        assert 0.01 < rounds[0]["point_s"] < 2.0, rounds[0]
        assert not result["holds"] and "bench time budget" in (result["stopped"] or ""), result["stopped"]
        assert not api.get("/bench/status")["busy"]
        api.close()
    finally:
        svc.stop()
