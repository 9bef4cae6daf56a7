"""REST of map quality and comparison (no bench: maps built in storage from stored results):
GET /maps/{id} with quality, ?smooth=outliers on the map and its exports, GET /maps/{a}/compare/{b}."""

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.calibration_service import CalibrationService
from service.settings import load_settings
from tests.support.maps import make_map, theta_of

GRID = {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 2000.0, 3000.0], "udc_v": [12.0]}
OUTLIER = (2.0, 2000.0, 12.0)


def smooth_theta(p):
    return theta_of(2.0 + 0.2 * p[0], 270.0 + p[1] / 200.0)


def with_outlier(p):
    return theta_of(6.0, 200.0) if p == OUTLIER else smooth_theta(p)


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    service = CalibrationService(
        load_settings(
            environ={},
            overrides={"emulator.speedup": 0.0, "server.db_path": str(tmp_path_factory.mktemp("maps") / "api.db")},
        )
    )
    with TestClient(create_app(service, manage_lifecycle=False)) as client:
        maps = {
            "smooth": make_map(service.storage, GRID, smooth_theta),
            "outlier": make_map(service.storage, GRID, with_outlier),
            "h12": make_map(service.storage, GRID, smooth_theta, harmonic_order=12),
        }
        yield client, maps


def test_map_shows_each_cells_quality_and_the_outlier_count(api):
    client, maps = api
    m = client.get(f"/api/v1/maps/{maps['outlier']}").json()
    assert m["quality"]["outliers"] == 1 and m["smoothed"] is False
    bad = [c for c in m["cells"] if c["quality"] == "outlier"]
    assert [(c["torque_nm"], c["speed_rpm"]) for c in bad] == [OUTLIER[:2]]
    assert "from the median of its 4 ok neighbours" in bad[0]["outlier_reason"]


def test_smoothed_view_and_export_mark_the_replaced_cell(api):
    client, maps = api
    m = client.get(f"/api/v1/maps/{maps['outlier']}?smooth=outliers").json()
    assert m["smoothed"] and m["quality"]["smoothed"] == 1
    cell = next(c for c in m["cells"] if c["quality"] == "smoothed")
    assert cell["smoothed_from"].startswith(f"median theta of the ok neighbours of map {maps['outlier']}")
    r = client.get(f"/api/v1/maps/{maps['outlier']}/export?format=csv&smooth=outliers")
    assert r.status_code == 200 and "SMOOTHED view" in r.text
    assert f'ripplecal_map{maps["outlier"]}_smoothed.csv' in r.headers["content-disposition"]
    # the stored map is unchanged
    assert client.get(f"/api/v1/maps/{maps['outlier']}").json()["quality"]["outliers"] == 1
    r = client.get(f"/api/v1/maps/{maps['outlier']}?smooth=always")
    assert r.status_code == 422 and any("smooth" in e["loc"] for e in r.json()["detail"])


def test_compare_two_maps(api):
    client, maps = api
    r = client.get(f"/api/v1/maps/{maps['smooth']}/compare/{maps['outlier']}")
    assert r.status_code == 200
    body = r.json()
    assert body["summary"]["compared"] == 9 and body["same_axes"]
    worst = body["summary"]["worst_cell"]
    assert (worst["torque_nm"], worst["speed_rpm"], worst["udc_v"]) == OUTLIER
    moved = [c for c in body["cells"] if c["delta_theta_deg"] > 0]
    assert len(moved) == 1 and moved[0]["predicted_suppression_db"] < body["cells"][0]["predicted_suppression_db"]


def test_a_map_compared_with_itself_is_allowed_with_zero_deltas(api):
    client, maps = api
    body = client.get(f"/api/v1/maps/{maps['smooth']}/compare/{maps['smooth']}").json()
    assert body["summary"]["max_delta_theta_deg"] == 0.0


@pytest.mark.parametrize("path", ["/api/v1/maps/999/compare/{smooth}", "/api/v1/maps/{smooth}/compare/999"])
def test_compare_with_a_missing_map_is_404_naming_it(api, path):
    client, maps = api
    r = client.get(path.format(**maps))
    assert r.status_code == 404 and r.json()["detail"] == "map 999 does not exist"


def test_maps_of_different_harmonics_are_422(api):
    client, maps = api
    r = client.get(f"/api/v1/maps/{maps['smooth']}/compare/{maps['h12']}")
    assert r.status_code == 422
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["path", "other_id"] and "h = 12" in detail["msg"]
