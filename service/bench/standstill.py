"""When a braked shaft is at standstill: the one criterion the run's make_safe (on the DAQ clock) and the
bench watchdog (on the load's own speed reading, wall clock) disable the load by.

A speed loop braking at its full ramp overshoots through zero (the PI's integral: an 8 Hz loop braking from
1000 rpm swings to about -40 rpm and settles within some 0.3 s). One reading below the threshold is then
the zero crossing, not standstill: a load disabled there coasts at the overshoot's speed, and a shaft that
coasts at 40 rpm against friction alone turns for half a minute. So the speed must stay below the
threshold for `HOLD_S`: longer than an overshoot's crossing, a small part of a run's end (once per run, not
per point). tests/e2e/test_standstill_e2e.py proves it with a 3 Hz load loop, whose crossing the one-reading
rule caught.
"""

from __future__ import annotations

STANDSTILL_RPM = 20.0  # |speed| below this ...
HOLD_S = 0.25  # ... for this long (the clock of the readings) is standstill


class StandstillJudge:
    """Feed (time_s, speed_rpm) readings in order; `update` says whether the shaft has been below
    `below_rpm` for `hold_s` up to that reading. Any reading at or above it starts the hold again."""

    def __init__(self, below_rpm: float = STANDSTILL_RPM, hold_s: float = HOLD_S):
        self.below_rpm = below_rpm
        self.hold_s = hold_s
        self._below_since_s: float | None = None

    def update(self, time_s: float, speed_rpm: float) -> bool:
        if not abs(speed_rpm) < self.below_rpm:  # NaN counts as turning
            self._below_since_s = None
            return False
        if self._below_since_s is None:
            self._below_since_s = time_s
        return time_s - self._below_since_s >= self.hold_s
