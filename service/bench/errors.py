"""What the bench raises (besides InterlockTripped, service/bench/interlocks.py)."""

from __future__ import annotations

from service.errors import BenchRefused, Conflict


class BenchError(Conflict, RuntimeError):
    pass


class BenchUnreachable(BenchRefused, BenchError):
    """connect() failed: str() is one line naming the device, its address and what to check."""


class RunError(BenchError):
    """A run failed and make_safe failed too: the message names the first cause, then make_safe's error."""
