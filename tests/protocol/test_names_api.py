"""Names through the API on both engines (issue 25, finding 7): a bench or schedule name with a NUL, a
newline or outer whitespace is a 422 saying what is wrong, on SQLite as on PostgreSQL (which answered
500 for a NUL, and took "bench-a\\n" as a new bench nobody serves); nothing of it is stored. Printable
names, accents and inner spaces included, are kept as they are on both."""

from __future__ import annotations

import pytest

from tests.support.live_app import bearer, client_for, started_service

OP = {"torque_nm": 1.0, "speed_rpm": 1000, "udc_v": 12}
SWEEP = {"grid": {"torque_nm": [1.0], "speed_rpm": [1000], "udc_v": [12]}, "method": "probe"}
BAD = [
    ("bench\x00a", "a control character (U+0000)"),
    ("bench-a\n", "a control character (U+000A)"),
    (" bench-a", "begins or ends with whitespace"),
]


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api(request, tmp_path_factory):
    """(client, operator headers) of a service on each engine (its own emulated bench, named A)."""
    directory = tmp_path_factory.mktemp(f"names-{request.param}")
    overrides = {"bench_name": "A"}
    if request.param == "postgresql":
        cluster = request.getfixturevalue("pg_cluster")
        if not cluster.running:
            cluster.start()
        overrides["server.db_path"] = cluster.create_database()
    with started_service(directory, **overrides) as service:
        yield client_for(service), bearer(service, "operator")


def refusal(r, says: str, what: str) -> str:
    assert r.status_code == 422, r.text
    messages = [item["msg"] for item in r.json()["detail"]]
    assert any(what in m and says in m for m in messages), messages
    return " ".join(messages)


@pytest.mark.parametrize("name, says", BAD)
def test_a_bench_name_with_a_nul_a_newline_or_outer_space_is_a_422_on_each_engine(api, name, says):
    client, auth = api
    bodies = {
        "/api/v1/identifications": {"operating_point": OP, "method": "probe", "bench": name},
        "/api/v1/sweeps": {**SWEEP, "bench": name},
        "/api/v1/schedules": {"name": f"for {len(name)}", "cron": "0 3 * * *", "sweep": SWEEP, "bench": name},
        # the body is refused before the map is looked for: none need exist
        "/api/v1/maps/1/validate": {"bench": name},
        "/api/v1/maps/1/refine": {"bench": name},
    }
    for path, body in bodies.items():
        refusal(client.post(path, json=body, headers=auth), says, "bench name")
    # nothing of it stored: no bench by that name, no job, no schedule
    assert name not in {b["name"] for b in client.get("/api/v1/benches").json()}
    assert all(j.get("bench") != name for j in client.get("/api/v1/jobs").json())
    assert all(s.get("bench") != name for s in client.get("/api/v1/schedules").json())


@pytest.mark.parametrize("name, says", BAD)
def test_a_schedule_name_is_held_to_the_same_rule_when_made_and_when_renamed(api, name, says):
    client, auth = api
    body = {"name": name, "cron": "0 3 * * *", "sweep": SWEEP}
    refusal(client.post("/api/v1/schedules", json=body, headers=auth), says, "schedule name")
    made = client.post("/api/v1/schedules", json={**body, "name": f"nightly {len(name)}"}, headers=auth)
    assert made.status_code == 201, made.text
    schedule_id = made.json()["id"]
    refusal(client.patch(f"/api/v1/schedules/{schedule_id}", json={"name": name}, headers=auth), says, "schedule name")
    assert client.get(f"/api/v1/schedules/{schedule_id}").json()["name"] == f"nightly {len(name)}"
    assert client.delete(f"/api/v1/schedules/{schedule_id}", headers=auth).status_code in (200, 204)


def test_printable_names_with_accents_and_inner_spaces_are_kept_on_each_engine(api):
    client, auth = api
    r = client.post(
        "/api/v1/identifications", json={"operating_point": OP, "method": "probe", "bench": "Prüfstand 2"}, headers=auth
    )
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["bench"] == "Prüfstand 2" and "bench Prüfstand 2" in job["waiting_for"]
    shown = {b["name"]: b for b in client.get("/api/v1/benches").json()}
    assert shown["Prüfstand 2"]["queue"] >= 1 and not shown["Prüfstand 2"]["online"]
    assert client.post(f"/api/v1/jobs/{job['id']}/cancel", headers=auth).status_code == 200
