"""The setpoint/sync-toggle accounting (service/bench/setpoint_accounting.py, service/bench/point_stream.PointStream)
on a real pty.

A DAQ that cannot wait (a real one, or the emulator paced) drops what the reader does not take in
time; a setpoint's sync toggle can fall into the hole. Across a gap only the level is seen, so toggles
go missing in pairs. Streams here are made with the emulator's frame encoder; the drive's count of
setpoints is the number the test says it wrote."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.daq_protocol import FLAG_SYNC_INPUT, encode_frames
from drivers.daq_reader import DaqReader
from service.bench.point_stream import PointStream
from service.bench.setpoint_accounting import (
    INITIAL_QUIET_SAMPLES,
    MAX_ESTABLISH_SAMPLES,
    MAX_QUIET_SAMPLES,
    MIN_QUIET_SAMPLES,
    AccountingError,
    SetpointAccounting,
)
from service.identification.session import MeasurementError
from tests.support.pty_writer import PtyWriter

RATE_HZ = 16000.0
QUIET = 4096  # samples of a quiet line after a gap that show no setpoint is pending


def stream(pieces: list[tuple[int, int]], seq_jumps: dict[int, int] | None = None) -> bytes:
    """Frames with the sync level of each piece [(samples, level)]; seq_jumps {sample: lost samples}
    cuts holes in the sequence before that sample."""
    levels = np.concatenate([np.full(n, level) for n, level in pieces])
    seq = np.arange(len(levels))
    for at, lost in (seq_jumps or {}).items():
        seq[at:] += lost
    return encode_frames(
        seq, (seq * 97) % 65536, np.zeros(len(seq), np.int64), np.where(levels == 1, FLAG_SYNC_INPUT, 0)
    )


class Drive:
    """The drive's side of the count as the accounting sees it: setpoints written, and the resync."""

    def __init__(self, written: int = 0):
        self.written = written
        self.resyncs: list[int] = []

    def resync(self, toggles_seen: int) -> dict:
        self.resyncs.append(toggles_seen)
        self.written = toggles_seen
        return {"commits_reported": 0, "commits_expected": None}


@pytest.fixture
def pty():
    writer = PtyWriter()
    yield writer
    writer.close()


def accounting_on(reader, drive: Drive, latency: int | None = QUIET // 2) -> SetpointAccounting:
    acc = SetpointAccounting(reader, 5.0, lambda: drive.written, drive.resync)
    acc.doubt_reason = None  # established (the tests below start from a known count)
    if latency is not None:
        acc.latencies.append(latency)  # quiet window = twice the largest recent latency
    return acc


def wait_for_effect(data: bytes, setpoints_written: int, max_plant_s: float = 2.0):
    writer = PtyWriter()
    try:
        with DaqReader(writer.path) as reader:
            writer.write_in_thread(data)
            acc = accounting_on(reader, Drive(setpoints_written))
            return PointStream(acc, RATE_HZ).wait_for_effect(max_plant_s), acc.cursor
    finally:
        writer.close()


def test_two_toggles_lost_in_a_gap_are_counted_once_the_line_is_quiet():
    # level 0, then 300 samples lost in which the drive applied two setpoints (0 -> 1 -> 0), then quiet
    effect, cursor = wait_for_effect(stream([(1000, 0), (QUIET + 3000, 0)], {1000: 300}), setpoints_written=2)
    assert cursor.toggles_hidden == 2 and cursor.toggles_seen == 2
    # the effect is taken after the hole and its quiet run (on the DAQ clock), never inside data from before it
    assert 1000 + 300 + QUIET - 1 <= effect < 1000 + 300 + QUIET + 4096


def test_a_toggle_after_the_gap_still_marks_the_exact_sample():
    # the one setpoint was applied after the hole: its toggle is seen and is the effect
    effect, cursor = wait_for_effect(stream([(1000, 0), (700, 0), (3000, 1)], {1000: 300}), setpoints_written=1)
    assert effect == 1000 + 300 + 700 and cursor.toggles_hidden == 0


def test_an_odd_count_after_a_gap_is_an_accounting_error_not_a_guess():
    # two setpoints written, one level change across the hole, then quiet: one toggle cannot hide alone
    with pytest.raises(MeasurementError, match="odd number"):
        wait_for_effect(stream([(1000, 0), (QUIET + 3000, 1)], {1000: 300}), setpoints_written=2)


def test_a_line_never_quiet_after_gaps_names_them():
    # holes every 1000 samples, the toggle never comes: the budget ends with the reason
    n = 40
    with pytest.raises(MeasurementError, match=r"toggle\(s\) missing; the stream had \d+ DAQ gap"):
        wait_for_effect(
            stream([(1000 * n, 0)], {1000 * k: 10 for k in range(1, n)}), setpoints_written=2, max_plant_s=1.5
        )


def test_the_budget_is_plant_time_on_the_sample_clock_not_samples_received():
    # 0.25 s of samples arrive, but the sequence spans 2.5 s (a hole of 2.25 s): a 1 s budget is spent
    data = stream([(2000, 0), (2000, 0)], {2000: int(2.25 * RATE_HZ)})
    with pytest.raises(MeasurementError, match="within 1 s of plant time"):
        wait_for_effect(data, setpoints_written=1, max_plant_s=1.0)


def test_nothing_pending_is_no_wait(pty):
    with DaqReader(pty.path) as reader:
        pty.write_in_thread(stream([(500, 0)]))
        acc = accounting_on(reader, Drive(0))
        points = PointStream(acc, RATE_HZ)
        assert points.wait_for_effect(1.0) == 0  # the next sample: nothing was written
        assert acc.cursor.toggles_seen == 0


def test_establishing_waits_for_a_quiet_line_sized_by_the_measured_latency(pty):
    # a previous master left setpoints applied at 100, 900 and 1700; then the line stays quiet, for as
    # long as a DAQ streams: establishing flushes what the reader has buffered (possibly all that was
    # written so far) and counts its quiet window from the gap the flush leaves
    data = stream([(100, 0), (800, 1), (800, 0), (100_000, 1)])
    with DaqReader(pty.path) as reader:
        pty.write_in_thread(data)
        drive = Drive(written=0)
        acc = SetpointAccounting(reader, 5.0, lambda: drive.written, drive.resync)
        assert acc.in_doubt  # at connect: nothing known
        acc.latencies.append(1000)  # a measured path: quiet window 2000 samples
        assert acc.quiet_samples() == 2000
        report = acc.establish(guard=lambda: None)
    assert not acc.in_doubt and report["quiet_samples"] == 2000
    # the three toggles were seen (the first data may be flushed: at most all three); the count is the drive's
    assert drive.resyncs == [acc.cursor.toggles_seen] and drive.written == acc.cursor.toggles_seen
    assert acc.cursor.last_index >= 1700 + 2000 - 1


def test_quiet_window_before_any_latency_is_the_conservative_one_then_follows_the_path():
    acc = SetpointAccounting(None, 1.0, lambda: 0, lambda n: {})
    assert acc.quiet_samples() == INITIAL_QUIET_SAMPLES
    acc.latencies.extend([40, 90, 60])
    assert acc.quiet_samples() == MIN_QUIET_SAMPLES  # a fast path: never below the floor
    acc.latencies.append(5000)
    assert acc.quiet_samples() == 10000
    # a latency timed while the reader lagged 3.7 s behind (a loaded PC: seen in the suite) asks no window
    # that a gap could keep from ever fitting into MAX_ESTABLISH_SAMPLES
    acc.latencies.append(58540)
    assert acc.quiet_samples() == MAX_QUIET_SAMPLES <= MAX_ESTABLISH_SAMPLES // 4


def test_a_line_that_never_goes_quiet_cannot_be_established(pty):
    toggling = [(300, k % 2) for k in range(500)]  # a toggle every 300 samples, 150000 samples
    with DaqReader(pty.path) as reader:
        pty.write_in_thread(stream(toggling))
        acc = SetpointAccounting(reader, 5.0, lambda: 0, lambda n: {})
        acc.latencies.append(1000)
        with pytest.raises(AccountingError, match="never stayed quiet"):
            acc.establish(guard=lambda: None)
    assert acc.in_doubt


def test_latency_of_each_setpoint_is_measured_from_its_write(pty):
    with DaqReader(pty.path) as reader:
        pty.write_in_thread(stream([(1000, 0), (3000, 1)]))
        drive = Drive(0)
        acc = accounting_on(reader, drive, latency=None)
        points = PointStream(acc, RATE_HZ)
        points.next_exact(400)  # read up to sample 399
        drive.written = 1
        acc.note_write(1)  # written when the newest sample read was 399
        assert points.wait_for_effect(1.0) == 1000
    assert list(acc.latencies) == [1000 - 399]


def test_a_run_starts_clean_when_the_line_kept_its_level_and_in_doubt_when_it_did_not(pty):
    data = stream([(2000, 1), (60000, 1)])  # longer than the reader and the pty hold: data follow each flush
    with DaqReader(pty.path, max_buffered_samples=1024) as reader:
        pty.write_in_thread(data)
        acc = accounting_on(reader, Drive(0))
        acc.cursor.read(100)  # the line was at level 1 when the last run ended
        acc.start_run(guard=lambda: None)
        assert not acc.in_doubt
        acc.cursor._level = 0  # as if it had been 0: something moved it meanwhile
        acc.start_run(guard=lambda: None)
        assert acc.in_doubt and "changed level" in acc.doubt_reason


def test_unconfirmed_setpoints_at_the_end_of_a_run_put_the_count_in_doubt():
    drive = Drive(0)
    acc = SetpointAccounting(None, 1.0, lambda: drive.written, drive.resync)
    acc.doubt_reason = None
    drive.written = 2
    acc.end_run()
    assert acc.in_doubt and "2 setpoint(s) unconfirmed" in acc.doubt_reason
