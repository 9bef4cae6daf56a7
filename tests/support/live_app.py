"""The real application for in-process API tests: CalibrationService on a SQLite file in tmp, its
emulator child started, the FastAPI app around it (no HTTP server needed: TestClient / ASGI)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.calibration_service import CalibrationService
from service.settings import load_settings
from tests.support.waiting import wait_run_finished


@contextlib.contextmanager
def started_service(db_dir: Path, **overrides) -> Iterator[CalibrationService]:
    service = CalibrationService(
        load_settings(
            environ={}, overrides={"emulator.speedup": 0.0, "server.db_path": str(db_dir / "api.db"), **overrides}
        )
    )
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
    return wait_run_finished(lambda: client.get(path).json(), timeout_s, path)
