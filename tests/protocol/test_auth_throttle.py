"""Wrong tokens throttled per client address (service/api/auth_throttle.py, issue 25 finding 8): after
`server.auth_max_failures` unknown or revoked tokens within `server.auth_failure_window_s`, that address
is answered 429 with Retry-After, whatever token it sends; other addresses are served as before.
Over HTTPS through the real server: tests/e2e/test_connections_e2e.py."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.api.auth_throttle import AuthThrottle
from service.calibration_service import CalibrationService
from service.settings import load_settings

ROUTE = "/api/v1/schedules/999"  # DELETE needs an operator token; no schedule 999: 404 once authenticated


class _Clock:
    def __init__(self) -> None:
        self.now = 500.0

    def __call__(self) -> float:
        return self.now


def test_ten_failures_in_a_minute_throttle_that_client_until_the_oldest_is_a_minute_old():
    clock = _Clock()
    throttle = AuthThrottle(max_failures=10, window_s=60, clock=clock)
    for _ in range(9):
        throttle.failed("10.0.0.5")
        clock.now += 1
    assert throttle.retry_after_s("10.0.0.5") is None  # nine: it may try again
    throttle.failed("10.0.0.5")  # the tenth, 9 s after the first
    assert throttle.retry_after_s("10.0.0.5") == 51
    assert throttle.retry_after_s("10.0.0.6") is None  # another client
    clock.now += 50.5
    assert throttle.retry_after_s("10.0.0.5") == 1  # whole seconds, rounded up
    clock.now += 0.5
    assert throttle.retry_after_s("10.0.0.5") is None  # the first failure is a minute old: one more try
    throttle.failed("10.0.0.5")
    assert throttle.retry_after_s("10.0.0.5") == 1  # and the next failure throttles it again at once


@pytest.fixture
def app(tmp_path):
    service = CalibrationService(
        load_settings(
            environ={},
            overrides={
                "emulator.speedup": 0.0,
                "server.db_path": str(tmp_path / "api.db"),
                "server.auth_max_failures": 3,
                "server.auth_failure_window_s": 60,
            },
        )
    )
    _, token = service.storage.create_token("operator")
    return create_app(service, manage_lifecycle=False), {"Authorization": f"Bearer {token}"}


def test_wrong_tokens_get_429_with_retry_after_and_another_client_is_served(app):
    app, operator = app
    guesser = TestClient(app, client=("10.0.0.5", 40000), raise_server_exceptions=False)
    other = TestClient(app, client=("10.0.0.6", 40000), raise_server_exceptions=False)
    for i in range(3):
        assert guesser.delete(ROUTE, headers={"Authorization": f"Bearer guess-{i}"}).status_code == 401
    r = guesser.delete(ROUTE, headers={"Authorization": "Bearer guess-3"})
    assert r.status_code == 429
    assert 1 <= int(r.headers["Retry-After"]) <= 60
    assert "10.0.0.5" in r.json()["detail"] and f"try again in {r.headers['Retry-After']} s" in r.json()["detail"]
    # throttled whatever it sends: a right token from it teaches it nothing
    assert guesser.delete(ROUTE, headers=operator).status_code == 429
    # no token is not a guess (401 as before); routes without a token are not throttled
    assert guesser.delete(ROUTE).status_code == 401
    assert guesser.get("/api/v1/benches").status_code == 200
    # another address: wrong tokens counted for it alone, the right one authenticated
    assert other.delete(ROUTE, headers={"Authorization": "Bearer guess"}).status_code == 401
    assert other.delete(ROUTE, headers=operator).status_code == 404


def test_429_is_documented_with_retry_after_where_a_token_is_checked(app):
    app, _ = app
    spec = TestClient(app).get("/openapi.json").json()
    answers = spec["paths"]["/api/v1/jobs/{job_id}/cancel"]["post"]["responses"]
    assert "401" in answers and "Retry-After" in answers["429"]["headers"]
    assert "429" not in spec["paths"]["/api/v1/jobs/{job_id}"]["get"]["responses"]  # no token, no throttle
