"""Shared by every test: the emulated bench runs as fast as its DAQ is read unless a test says otherwise.

The service's default is the real bench's clock (`emulator.speedup = 1`). Tests measure behaviour, not
bench time, so they run the emulator at speedup 0 (plant time stops while nobody reads: nothing is lost,
the same results) through the environment every service and CLI process of the session inherits; the
tests that prove real-time behaviour pass `--speedup 1` themselves (tests/e2e/test_realtime_e2e.py).

Fixtures shared by several modules:
- `live`: the real app around a started CalibrationService (tests/support/live_app.py), one per module:
  (service, TestClient, operator headers). A module passes settings overrides of its own in a
  module-level dict `LIVE_SETTINGS`."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("RIPPLECAL_EMULATOR__SPEEDUP", "0")


@pytest.fixture(scope="module")
def live(request, tmp_path_factory):
    # imported here: the unit tests never need the application (nor its import time)
    from tests.support.live_app import bearer, client_for, started_service

    overrides = getattr(request.module, "LIVE_SETTINGS", {})
    name = request.module.__name__.rsplit(".", 1)[-1]
    with started_service(tmp_path_factory.mktemp(name), **overrides) as service:
        yield service, client_for(service), bearer(service, "operator")
