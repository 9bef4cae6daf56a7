"""The standstill criterion (service/bench/standstill.py): below the threshold for the hold time, not at one
reading; the readings of a PI loop's overshoot through zero are not standstill."""

from __future__ import annotations

import math

from service.bench.standstill import HOLD_S, STANDSTILL_RPM, StandstillJudge


def test_a_crossing_through_zero_is_not_standstill_a_held_low_speed_is():
    judge = StandstillJudge()
    # braking at 20000 rpm/s through zero to -40 rpm, 2 ms steps: below 20 rpm for 2 ms only
    t, speeds = 0.0, [100.0, 60.0, 20.0, -19.9, -20.0, -40.0, -40.0]
    for rpm in speeds:
        assert not judge.update(t, rpm)
        t += 0.002
    # then held at 5 rpm: not before HOLD_S has passed since the first low reading, then yes
    first_low = t
    while t - first_low < HOLD_S - 1e-9:
        assert not judge.update(t, 5.0)
        t += 0.02
    assert judge.update(first_low + HOLD_S, 5.0)


def test_any_reading_at_or_above_the_threshold_or_unreadable_starts_the_hold_again():
    judge = StandstillJudge()
    assert not judge.update(0.0, 0.0)
    assert not judge.update(0.9 * HOLD_S, STANDSTILL_RPM)  # at the threshold: turning
    assert not judge.update(1.5 * HOLD_S, 0.0)
    assert not judge.update(2.0 * HOLD_S, math.nan)  # NaN: turning
    assert not judge.update(2.1 * HOLD_S, -1.0)
    assert not judge.update(3.0 * HOLD_S, 1.0)
    assert judge.update(3.1 * HOLD_S, 1.0)
