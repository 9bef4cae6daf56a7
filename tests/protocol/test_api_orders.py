"""`orders` on the requests (DESIGN section 6: a sweep, identification, map, run-up and LUT carry the list of
harmonic orders, default [6]): several orders need a method that cancels several at once (probe-orders, the
method when none is named); the bench's harmonic order is among them; a method of one order takes one."""

from __future__ import annotations

import pytest

from tests.support.live_app import wait_finished

OP = {"torque_nm": 2.5, "speed_rpm": 1500, "udc_v": 12}


def test_an_identification_of_two_orders_names_them_and_judges_each(live):
    _, client, operator = live
    r = client.post("/api/v1/identifications", headers=operator, json={"operating_point": OP, "orders": [6, 12]})
    assert r.status_code == 202, r.text
    job = wait_finished(client, f"/api/v1/jobs/{r.json()['id']}", 300)
    assert job["request"]["method"] == "probe-orders" and job["request"]["options"]["orders"] == [6, 12], job
    result = job["result"]
    assert [o["order"] for o in result["orders"]] == [6, 12], result
    assert all(o["status"] != "ok" or o["suppression_db"] >= o["target_db"] for o in result["orders"]), result


def test_a_sweep_of_two_orders_says_them_and_one_of_one_order_says_its_own(live):
    _, client, operator = live
    grid = {"torque_nm": [2.5], "speed_rpm": [1500], "udc_v": [12]}
    two = client.post("/api/v1/sweeps", headers=operator, json={"grid": grid, "orders": [6, 12]})
    assert two.status_code == 202, two.text
    assert two.json()["orders"] == [6, 12] and two.json()["method"] == "probe-orders"
    client.post(f"/api/v1/sweeps/{two.json()['id']}/cancel", headers=operator)
    one = client.post("/api/v1/sweeps", headers=operator, json={"grid": grid, "orders": [6], "method": "probe"})
    assert one.status_code == 202, one.text
    assert one.json()["orders"] == [6]
    client.post(f"/api/v1/sweeps/{one.json()['id']}/cancel", headers=operator)


@pytest.mark.parametrize(
    "body, needle",
    [
        ({"orders": [6, 12], "method": "probe"}, "method probe cancels one order; probe-orders cancels several"),
        ({"orders": [12]}, "orders [12] do not include this bench's harmonic order 6"),
        ({"orders": [6, 6]}, "orders [6, 6] name an order twice"),
        ({"orders": [6, 99]}, "must be at most 48"),
        ({"orders": [6, 12, 18, 24, 30]}, "too long: at most 4"),
    ],
)
@pytest.mark.parametrize("path", ["/api/v1/identifications", "/api/v1/sweeps"])
def test_orders_a_run_cannot_take_are_422_at_body_orders(live, path, body, needle):
    _, client, operator = live
    target = (
        {"operating_point": OP}
        if path.endswith("identifications")
        else {"grid": {"torque_nm": [2.5], "speed_rpm": [1500]}}
    )
    r = client.post(path, headers=operator, json={**target, **body})
    assert r.status_code == 422, r.text
    [item] = r.json()["detail"]
    assert item["loc"][:2] == ["body", "orders"] and needle in item["msg"], item
