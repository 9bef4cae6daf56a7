"""An interlock's trip as the bench records it, and the error a run stops (or is refused) with.

A `Trip` is made by the interlock monitor (service/bench/interlock_monitor.py) when an interlock
(service/bench/interlocks.py) trips, and by the bench for what else forbids a run (a bench never
reached, the watchdog's stop); `InterlockTripped` carries the first cause up to the run's caller.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from service.errors import BenchRefused


@dataclass(frozen=True)
class Trip:
    """One interlock trip: which interlock, why (the first cause), whether a person must acknowledge it."""

    interlock: str
    reason: str
    latched: bool
    at: str  # ISO 8601 UTC
    monotonic: float

    def public(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("monotonic")
        return d


class InterlockTripped(BenchRefused, RuntimeError):
    """A run stopped (or was refused) because an interlock tripped; str() is the first cause."""

    def __init__(self, trip: Trip, refused: bool = False, outcome: str | None = None):
        self.trip = trip
        self.refused = refused
        self.outcome = outcome  # make_safe's outcome, added to (never substituted for) the cause
        prefix = "refused: interlock tripped: " if refused else "interlock tripped: "
        # only a person clears a latched trip: a refusal says how
        hint = "; a person acknowledges it: POST /api/v1/bench/fault-reset" if refused and trip.latched else ""
        super().__init__(prefix + trip.reason + hint + (f"; {outcome}" if outcome else ""))
