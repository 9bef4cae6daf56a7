"""REST of POST /sweeps/preview and the sweep request's `regime`: the real app around a service whose
engine is real but never started (no bench, no emulator: a queued sweep stays queued), so POST /sweeps
goes through Engine.submit_sweep and what it stores can be held against the preview."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.calibration_service import CalibrationService
from service.runs.engine import Engine
from service.runs.plans import Grid, SweepPlan
from service.settings import load_settings

EXAMPLE = {
    "grid": {"torque_nm": [1, 2, 3, 4], "speed_rpm": [1000, 1400, 1800, 2200, 2600], "udc_v": [12]},
    "method": "adaptive",
    # 3 and 4 Nm at 2600 rpm are beyond what the motor settings hold at 12 V (test_envelope_...)
    "options": {"override_envelope_model": True},
    "regime": {"speeds_around_onset": True, "spacing_rpm": 100},
}


class _NoBench:
    identity = "protocol:no-bench"

    def check_reachable(self) -> None:  # a bench that was reached at start
        pass


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    service = CalibrationService(
        load_settings(
            environ={},
            overrides={"emulator.speedup": 0.0, "server.db_path": str(tmp_path_factory.mktemp("preview") / "api.db")},
        )
    )
    service.engine = Engine(service.storage, _NoBench(), service.settings, service.broker)  # never started
    _, token = service.storage.create_token("operator")
    with TestClient(create_app(service, manage_lifecycle=False), raise_server_exceptions=False) as client:
        yield client, {"Authorization": f"Bearer {token}"}, service


def _preview(client, body):
    r = client.post("/api/v1/sweeps/preview", json=body)
    assert r.status_code == 200, r.text
    return r.json()


def test_preview_answers_the_plan_without_a_token_and_queues_nothing(api):
    client, _, service = api
    before = (client.get("/api/v1/sweeps").json(), client.get("/api/v1/jobs").json())
    p = _preview(client, EXAMPLE)
    assert (client.get("/api/v1/sweeps").json(), client.get("/api/v1/jobs").json()) == before
    assert p["accepted"] is True and p["problems"] == []
    assert p["added_speeds_rpm"] == [1760.0, 1860.0, 1960.0, 2060.0, 2160.0, 2260.0]
    assert p["grid"]["speed_rpm"] == sorted(set(EXAMPLE["grid"]["speed_rpm"]) | set(p["added_speeds_rpm"]))
    assert p["requested_grid"]["speed_rpm"] == [1000.0, 1400.0, 1800.0, 2200.0, 2600.0]
    assert [(o["torque_nm"], o["onset_rpm"], o["placed_rpm"]) for o in p["onsets"]] == [
        (1.0, 2158.7, 2160.0),
        (2.0, 2064.6, 2060.0),
        (3.0, 1965.0, 1960.0),
        (4.0, 1862.0, 1860.0),
    ]
    assert p["voltage_margin"] == 0.95
    marked = {v["speed_rpm"]: v for v in p["speed_axis"]}
    assert marked[1860.0]["added"] and any("onset of 4 Nm at 12 V" in r for r in marked[1860.0]["reasons"])
    assert not marked[1800.0]["added"] and marked[1800.0]["reasons"] == []
    # the points in measuring order: U_dc, then torque, speed innermost alternating (plans.settling_order)
    plan = SweepPlan.from_grid(Grid.model_validate(p["grid"]))
    assert p["points"] == [op.model_dump() for op in plan.points] and p["total"] == 44
    speeds = p["grid"]["speed_rpm"]
    assert p["points"][: 2 * len(speeds)] == [{"torque_nm": 1.0, "speed_rpm": n, "udc_v": 12.0} for n in speeds] + [
        {"torque_nm": 2.0, "speed_rpm": n, "udc_v": 12.0} for n in reversed(speeds)
    ]
    est = p["estimate"]
    assert est["estimated_s"] == pytest.approx(3 + 44 * 0.9, abs=0.05) and est["worst_case_s"] > est["estimated_s"]
    assert est["basis"].startswith("estimate at speedup 1")


def test_post_sweeps_with_the_regime_stores_the_grid_the_preview_showed(api):
    client, operator, service = api
    p = _preview(client, EXAMPLE)
    r = client.post("/api/v1/sweeps", json=EXAMPLE, headers=operator)
    assert r.status_code == 202, r.text
    s = r.json()
    assert s["grid"] == p["grid"] and s["progress"]["total"] == p["total"] and s["state"] == "queued"
    stored = service.storage.get_sweep(s["id"])
    assert stored["grid"] == p["grid"]
    # without the regime: the grid as requested, the preview shows no added speed but the onsets
    plain = {k: v for k, v in EXAMPLE.items() if k != "regime"}
    p0 = _preview(client, plain)
    assert p0["added_speeds_rpm"] == [] and p0["grid"] == p0["requested_grid"] and len(p0["onsets"]) == 4
    s0 = client.post("/api/v1/sweeps", json=plain, headers=operator).json()
    assert s0["grid"] == p0["grid"] and s0["progress"]["total"] == 20


@pytest.mark.parametrize(
    "body",
    [
        {"grid": {"torque_nm": [1, 9], "speed_rpm": [50, 2000]}},  # bench limits
        {
            "grid": {"torque_nm": [1 + 0.1 * k for k in range(20)], "speed_rpm": [1000 + 80 * k for k in range(20)]},
            "method": "probe",
            "regime": {"speeds_around_onset": True},
        },  # 400 points, more once placed
        {
            "grid": {"torque_nm": [1, 2, 3, 4], "speed_rpm": [1000 + 7 * k for k in range(199)]},
            "confirm_large": True,
            "regime": {"speeds_around_onset": True},
        },  # > 200 speeds once placed
        {
            "grid": {"torque_nm": [2.5], "speed_rpm": [2000]},
            "method": "probe",
            "options": {"max_newton_steps": 50, "max_window_s": 5, "settle_s": 2},
        },  # plant time
        {"grid": {"torque_nm": [-2.5, 2.5, 5], "speed_rpm": [5000, 6000]}},  # no point inside the envelope model
    ],
)
def test_preview_problems_are_the_422_items_post_sweeps_answers(api, body):
    client, operator, _ = api
    p = _preview(client, body)
    r = client.post("/api/v1/sweeps", json=body, headers=operator)
    assert r.status_code == 422, r.text
    assert not p["accepted"] and p["problems"] == r.json()["detail"]


def test_the_placed_speeds_count_in_the_sweep_size(api):
    client, operator, _ = api
    body = {
        "grid": {"torque_nm": [1 + 0.1 * k for k in range(20)], "speed_rpm": [1000 + 80 * k for k in range(20)]},
        "method": "probe",
        "regime": {"speeds_around_onset": True},
    }
    r = client.post("/api/v1/sweeps", json=body, headers=operator)
    [item] = r.json()["detail"]
    assert item["loc"] == ["body", "confirm_large"] and "more than 400" in item["msg"]
    # confirmed, it goes (and is then cancelled: the engine never runs it)
    s = client.post("/api/v1/sweeps", json={**body, "confirm_large": True}, headers=operator).json()
    assert s["progress"]["total"] == _preview(client, body)["total"] > 400
    assert client.post(f"/api/v1/sweeps/{s['id']}/cancel", headers=operator).json()["state"] == "cancelled"
    r = client.post(
        "/api/v1/sweeps",
        json={
            "grid": {"torque_nm": [1, 2, 3, 4], "speed_rpm": [1000 + 7 * k for k in range(199)]},
            "regime": {"speeds_around_onset": True},
        },
        headers=operator,
    )
    [item] = r.json()["detail"]
    assert item["loc"] == ["body", "regime"] and "more than the grid's 200" in item["msg"]


@pytest.mark.parametrize(
    "regime,loc",
    [
        ({"speeds_around_onset": True, "spacing_rpm": 5}, ["body", "regime", "spacing_rpm"]),
        ({"speeds_around_onset": True, "spacing_rpm": float("inf")}, ["body", "regime", "spacing_rpm"]),
        ({"round_rpm": 0}, ["body", "regime", "round_rpm"]),
        ({"speeds_around_onset": True, "spacing": 100}, ["body", "regime", "spacing"]),
        ({"speeds_around_onset": "maybe"}, ["body", "regime", "speeds_around_onset"]),
    ],
)
@pytest.mark.parametrize("path", ["/api/v1/sweeps/preview", "/api/v1/sweeps"])
def test_bad_regime_fields_are_422_at_the_field(api, regime, loc, path):
    client, operator, _ = api
    raw = json.dumps({**EXAMPLE, "regime": regime}).replace("Infinity", "1e999")  # JSON's way to overflow
    r = client.post(path, content=raw, headers={**operator, "Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert loc in [e["loc"] for e in r.json()["detail"]]


@pytest.mark.parametrize(
    "grid",
    [
        {"torque_nm": [1], "speed_rpm": [0, -100, 2000]},
        {"torque_nm": [1e300, -1e300], "speed_rpm": [1e300], "udc_v": [1e300, 1e-300]},
        {
            "torque_nm": [float(k) for k in range(200)],
            "speed_rpm": [float(k) for k in range(1, 201)],
            "udc_v": [float(k) for k in range(1, 51)],
        },
    ],
)
def test_absurd_grids_are_answered_never_a_server_error(api, grid):
    client, _, _ = api
    p = _preview(client, {"grid": grid, "regime": {"speeds_around_onset": True}})
    assert not p["accepted"] and p["problems"]
    assert p["points"] == [] or p["estimate"] is not None


def test_openapi_documents_every_field_of_the_preview(api):
    client, _, _ = api
    spec = client.get("/openapi.json").json()
    op = spec["paths"]["/api/v1/sweeps/preview"]["post"]
    assert "security" not in op or op["security"] in ([], [{}])
    schemas = spec["components"]["schemas"]
    for name in ("SweepPreview", "RegimePlacement", "OnsetPrediction", "SpeedValue", "BenchTimeEstimate"):
        props = schemas[name]["properties"]
        missing = [f for f, v in props.items() if not v.get("description")]
        assert not missing, f"{name}: fields without a description: {missing}"
    regime = schemas["RegimePlacement"]["properties"]
    assert regime["spacing_rpm"]["minimum"] == 10 and regime["spacing_rpm"]["maximum"] == 2000


def test_points_outside_the_envelope_of_the_motor_settings_are_not_run_unless_overridden(api):
    """Issue 25: -2.5 and 2.5 Nm at 5000 rpm, 5 Nm at 6000 rpm (limits 5 Nm, 6000 rpm, 12 V) were accepted while
    the preview's own note said 5 Nm is not reached at any speed. A point the envelope model refuses (the back-EMF
    above what the DC link holds, a torque beyond the voltage and current limits) is listed with its reason and
    never run, as a full-load curve clips a bench's grid; a grid with no point inside is refused; a single point
    outside is refused. The override lets the model pass (a machine that exceeds its settings), never the hard
    limits."""
    client, operator, _ = api
    body = {"grid": {"torque_nm": [-2.5, 2.5, 5], "speed_rpm": [2600, 5000, 6000]}, "method": "probe"}
    p = _preview(client, body)
    assert p["accepted"] and p["problems"] == [], p["problems"]
    not_run = {
        (c["operating_point"]["torque_nm"], c["operating_point"]["speed_rpm"]): c["reason"] for c in p["not_run"]
    }
    assert set(not_run) == {(t, n) for t in (-2.5, 2.5, 5) for n in (5000, 6000)} | {(5, 2600)}, sorted(not_run)
    assert "back-EMF exceeds what the DC link holds" in not_run[(2.5, 5000)]
    assert "up to 3266 rpm at 12 V" in not_run[(2.5, 5000)]
    # 5 Nm at 2600 rpm: 2.58 Nm at most (the voltage limit with field weakening), beyond 20 % of the command
    assert "holds at most 2.58 Nm" in not_run[(5, 2600)] and "override_envelope_model" in not_run[(5, 2600)]
    assert _preview(client, {**body, "options": {"override_envelope_model": True}})["not_run"] == []
    outside = {"grid": {"torque_nm": [-2.5, 2.5, 5], "speed_rpm": [5000, 6000]}, "method": "probe"}
    p = _preview(client, outside)
    assert not p["accepted"] and [e["type"] for e in p["problems"]] == ["value_error.envelope"], p["problems"]
    assert "every one of the 6 point(s)" in p["problems"][0]["msg"]
    assert "override_envelope_model" in client.post("/api/v1/sweeps", json=outside, headers=operator).text
    assert _preview(client, {**outside, "options": {"override_envelope_model": True}})["accepted"] is True
    one = {"operating_point": {"torque_nm": -2.5, "speed_rpm": 5000, "udc_v": 12}, "method": "probe"}
    r = client.post("/api/v1/identifications", json=one, headers=operator)
    assert r.status_code == 422 and r.json()["detail"][0]["type"] == "value_error.envelope", r.text
    # the override is for the model only: 6 Nm stays refused by the bench limit
    hard = {"grid": {"torque_nm": [6.0], "speed_rpm": [2000]}, "options": {"override_envelope_model": True}}
    assert [e["type"] for e in _preview(client, hard)["problems"]] == ["value_error.bench_limits"]
