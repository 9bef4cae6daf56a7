"""The real application for in-process API tests: CalibrationService on a SQLite file in tmp, its
emulator child started, the FastAPI app around it (no HTTP server needed: TestClient / ASGI)."""
from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Iterator

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.calibration_service import CalibrationService
from service.settings import load_settings


@contextlib.contextmanager
def started_service(db_dir: Path, **overrides) -> Iterator[CalibrationService]:
    service = CalibrationService(load_settings(environ={}, overrides={"emulator.speedup": 0.0, "server.db_path": str(db_dir / "api.db"),
                                                                      **overrides}))
    service.start(status_period_s=None)
    try:
        yield service
    finally:
        service.stop()


def client_for(service: CalibrationService) -> TestClient:
    # the service is started by the fixture, not by the app's lifespan (one emulator per module)
    return TestClient(create_app(service, manage_lifecycle=False), raise_server_exceptions=False)


def bearer(service: CalibrationService, role: str) -> dict[str, str]:
    _, token = service.storage.create_token(role)
    return {"Authorization": f"Bearer {token}"}


def wait_finished(client: TestClient, path: str, timeout_s: float = 120.0) -> dict:
    """Poll a job or sweep until it leaves queued/running/paused (the timeout only guards a hang)."""
    deadline = time.monotonic() + timeout_s
    while True:
        body = client.get(path).json()
        if body["state"] not in ("queued", "running", "paused"):
            return body
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} still {body['state']} after {timeout_s} s")
        time.sleep(0.1)
