"""The setpoint/sync-toggle accounting of OperatingPointSession across DAQ gaps, on a real pty.

A DAQ that cannot wait (a real one, or the emulator paced) drops what the reader does not take in
time; a setpoint's sync toggle can fall into the hole. Across a gap only the level is seen, so toggles
go missing in pairs. Streams here are made with the emulator's frame encoder; the drive's count of
setpoints is the number the test says it wrote."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.daq_protocol import FLAG_SYNC_INPUT, encode_frames
from drivers.daq_reader import DaqReader
from service.identification.session import MeasurementError
from service.measurement import DaqCursor, OperatingPointSession
from tests.support.pty_writer import PtyWriter

RATE_HZ = 16000.0
QUIET = 4096          # samples of a quiet line after a gap that show no setpoint is pending


def stream(pieces: list[tuple[int, int]], seq_jumps: dict[int, int] | None = None) -> bytes:
    """Frames with the sync level of each piece [(samples, level)]; seq_jumps {sample: lost samples}
    cuts holes in the sequence before that sample."""
    levels = np.concatenate([np.full(n, level) for n, level in pieces])
    seq = np.arange(len(levels))
    for at, lost in (seq_jumps or {}).items():
        seq[at:] += lost
    return encode_frames(seq, (seq * 97) % 65536, np.zeros(len(seq), np.int64),
                         np.where(levels == 1, FLAG_SYNC_INPUT, 0))


def wait_for_effect(data: bytes, setpoints_written: int, max_plant_s: float = 2.0):
    writer = PtyWriter()
    try:
        with DaqReader(writer.path) as reader:
            writer.write_in_thread(data)
            cursor = DaqCursor(reader, read_timeout_s=5.0)
            session = OperatingPointSession(cursor, lambda c, s: None, lambda: setpoints_written, 6, RATE_HZ, 5,
                                            sync_quiet_samples=QUIET)
            return session.wait_for_effect(max_plant_s), cursor
    finally:
        writer.close()


def test_two_toggles_lost_in_a_gap_are_counted_once_the_line_is_quiet():
    # level 0, then 300 samples lost in which the drive applied two setpoints (0 -> 1 -> 0), then quiet
    effect, cursor = wait_for_effect(stream([(1000, 0), (QUIET + 3000, 0)], {1000: 300}), setpoints_written=2)
    assert cursor.toggles_hidden == 2 and cursor.toggles_seen == 2
    # the effect is taken after the hole and its quiet run, never inside data from before it
    assert 1000 + 300 + QUIET - 1 <= effect < 1000 + 300 + QUIET + 512


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
        wait_for_effect(stream([(1000 * n, 0)], {1000 * k: 10 for k in range(1, n)}), setpoints_written=2,
                        max_plant_s=1.5)
