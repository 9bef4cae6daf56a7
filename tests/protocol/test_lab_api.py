"""A lab through the API of one service (its emulated bench, SQLite): GET /benches shows it; a run posted
for another bench is stored, says what it waits for, and is never run here (service/runs/lab.py)."""

from __future__ import annotations

import time

import pytest

from service import __version__
from tests.support.live_app import bearer, client_for, started_service, wait_finished

OP = {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    with started_service(tmp_path_factory.mktemp("lab"), bench_name="A") as service:
        yield service, client_for(service), bearer(service, "operator")


def test_benches_shows_this_bench_online_with_its_version(lab):
    service, client, _ = lab
    benches = client.get("/api/v1/benches").json()
    me = next(b for b in benches if b["name"] == "A")
    assert me["online"] and me["own"] and me["seen"] == "online"
    assert me["software_version"] == __version__ and me["state"] in ("idle", "busy")
    assert client.get("/api/v1/version").json()["bench_name"] == "A"


def test_a_job_for_another_bench_waits_and_is_not_run_here(lab):
    service, client, auth = lab
    r = client.post("/api/v1/identifications", json={"operating_point": OP, "bench": "other"}, headers=auth)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and job["bench"] == "other"
    assert job["waiting_for"] == "bench other (never seen: no service has served it)"
    # limits a foreign bench may have differently are its service's to check: accepted here
    far = {"torque_nm": 2.5, "speed_rpm": 9000, "udc_v": 12}
    post = lambda body: client.post("/api/v1/identifications", json=body, headers=auth)  # noqa: E731
    assert post({"operating_point": far, "bench": "other"}).status_code == 202
    assert post({"operating_point": far}).status_code == 422
    time.sleep(2.0)  # several of the worker's claim polls
    assert client.get(f"/api/v1/jobs/{job['id']}").json()["state"] == "queued"
    other = next(b for b in client.get("/api/v1/benches").json() if b["name"] == "other")
    assert other["queue"] == 2 and not other["online"] and other["state"] == "unknown"
    # cancelled from here: no service had taken it
    r = client.post(f"/api/v1/jobs/{job['id']}/cancel", headers=auth)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"


def test_a_sweep_for_another_bench_waits_and_a_pause_is_asked_of_its_service(lab):
    service, client, auth = lab
    body = {"grid": {"torque_nm": [1, 2], "speed_rpm": [1000], "udc_v": [12]}, "bench": "other"}
    r = client.post("/api/v1/sweeps", json=body, headers=auth)
    assert r.status_code == 202, r.text
    sweep = r.json()
    assert sweep["state"] == "queued" and sweep["bench"] == "other" and "bench other" in sweep["waiting_for"]
    # pause: written for bench other's service to act on (nobody serves it here: it stays asked)
    r = client.post(f"/api/v1/sweeps/{sweep['id']}/pause", headers=auth)
    assert r.status_code == 200 and r.json()["control_request"] == "pause" and r.json()["state"] == "queued"
    r = client.post(f"/api/v1/sweeps/{sweep['id']}/resume", headers=auth)  # checked by the table here
    assert r.status_code == 409 and "not paused or interrupted" in r.json()["detail"]
    # cancel: no service has taken it, so it ends here
    r = client.post(f"/api/v1/sweeps/{sweep['id']}/cancel", headers=auth)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    # a placement around the field-weakening onset needs that bench's machine: refused here
    r = client.post("/api/v1/sweeps", json={**body, "regime": {"speeds_around_onset": True}}, headers=auth)
    assert r.status_code == 422 and "post it to its service" in r.text


def test_own_bench_runs_its_job_and_names_itself(lab):
    service, client, auth = lab
    r = client.post("/api/v1/identifications", json={"operating_point": OP, "method": "probe"}, headers=auth)
    assert r.status_code == 202, r.text
    assert r.json()["bench"] == "A" and r.json()["waiting_for"] is None
    job = wait_finished(client, f"/api/v1/jobs/{r.json()['id']}")
    assert job["state"] == "done", job


def test_a_schedule_names_its_bench(lab):
    service, client, auth = lab
    body = {
        "name": "lab nightly",
        "cron": "0 2 * * *",
        "sweep": {"grid": {"torque_nm": [1], "speed_rpm": [1000], "udc_v": [12]}},
        "bench": "other",
    }
    r = client.post("/api/v1/schedules", json=body, headers=auth)
    assert r.status_code == 201, r.text
    assert r.json()["bench"] == "other"
    mine = client.post("/api/v1/schedules", json={**body, "name": "mine", "bench": None}, headers=auth).json()
    assert mine["bench"] == "A"
