"""Shared by every test: the emulated bench runs as fast as its DAQ is read unless a test says otherwise.

The service's default is the real bench's clock (`emulator.speedup = 1`). Tests measure behaviour, not
bench time, so they run the emulator at speedup 0 (plant time stops while nobody reads: nothing is lost,
the same results) through the environment every service and CLI process of the session inherits; the
tests that prove real-time behaviour pass `--speedup 1` themselves (tests/e2e/test_realtime_e2e.py)."""
from __future__ import annotations

import os

os.environ.setdefault("RIPPLECAL_EMULATOR__SPEEDUP", "0")
