"""Plant time of one operating point, on the DAQ sample clock.

Plant time is counted from the sample at which each setpoint took effect to the end of the last
sample consumed under it; a segment without a new setpoint (`start_segment_at_next`) counts from
the next sample read. What precedes an effect is stale. Every duration is a difference of DAQ sample
indices, so a gap in the stream (frames lost) counts as the plant time it was, never as less.
"""

from __future__ import annotations


class PlantClock:
    """The plant-time and stale-sample bookkeeping of one point (module doc); knows no stream."""

    def __init__(self, sample_rate_hz: float):
        self.sample_rate_hz = sample_rate_hz
        self._segment_start: int | None = None
        self._segment_at_next = False
        self._plant_samples = 0
        self.stale_samples = 0

    def samples_for(self, seconds: float) -> int:
        return int(round(seconds * self.sample_rate_hz))

    def consume(self, first_index: int) -> bool:
        """Samples from `first_index` on are handed out: a segment waiting for the next sample starts
        there. True if they count as plant time (a setpoint has taken effect)."""
        if self._segment_at_next:
            self._segment_start = first_index
            self._segment_at_next = False
        return self.counting

    @property
    def counting(self) -> bool:
        """Whether what is consumed now counts as plant time."""
        return self._segment_start is not None

    def stale(self, n: int) -> None:
        """n samples consumed before a setpoint's effect (or dropped): not plant time."""
        self.stale_samples += n

    def count_until(self, end_index: int) -> None:
        if self._segment_start is not None and end_index >= self._segment_start:
            self._plant_samples += end_index - self._segment_start + 1
            self._segment_start = end_index + 1

    def start_segment_at_next(self) -> None:
        """Count plant time from the next sample read (a measurement under the setpoint in force)."""
        self._segment_start = None
        self._segment_at_next = True

    def start_segment(self, index: int) -> None:
        self._segment_start = index
        self._segment_at_next = False

    def end_segment(self) -> None:
        self._segment_start = None
        self._segment_at_next = False

    @property
    def plant_time_s(self) -> float:
        return self._plant_samples / self.sample_rate_hz

    def reset_plant_time(self) -> None:
        self._plant_samples = 0
