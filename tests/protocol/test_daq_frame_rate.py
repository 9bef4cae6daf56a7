"""The DAQ's frame rate checked at connect (DaqReader.check_frame_rate) against a real pty, no mocks.

A writer thread streams frames made by drivers.daq_protocol.encode_frames at a steady rate on the wall
clock, as a DAQ does (PtyWriter.write_at_rate), or as fast as they are read, as the emulator at
--speedup 0 does (PtyWriter.write_in_thread); the reader opens the slave by its /dev/pts path.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from drivers import daq_reader
from drivers.daq_protocol import FRAME_BYTES, encode_frames
from drivers.daq_reader import DaqNotSerialPort, DaqNotStreaming, DaqRateMismatch, DaqReader
from tests.support.pty_writer import PtyWriter

RATE_HZ = 16_000
PIECE_FRAMES = 32  # 2 ms of stream per write at 16 kHz, as the emulator's paced writes


def frames(seconds: float, rate_hz: float = RATE_HZ) -> bytes:
    n = int(seconds * rate_hz)
    zeros = np.zeros(n, dtype=np.int64)
    return encode_frames(np.arange(n), (np.arange(n) * 977) % 65536, zeros, zeros)


def worst_case_s() -> float:
    """Stream the check may read: its settle, its window and a confirming window, with room for a
    loaded PC."""
    return 2 * (daq_reader.FRAME_RATE_SETTLE_S + daq_reader.FRAME_RATE_WINDOW_S + daq_reader.FRAME_RATE_CONFIRM_S)


@pytest.fixture
def pty_writer():
    writer = PtyWriter()
    yield writer
    writer.close()


def paced(writer: PtyWriter, rate_hz: float) -> None:
    writer.write_at_rate(frames(worst_case_s(), rate_hz), PIECE_FRAMES * FRAME_BYTES, rate_hz * FRAME_BYTES)


def test_a_daq_at_its_configured_rate_passes(pty_writer):
    paced(pty_writer, RATE_HZ)
    with DaqReader(pty_writer.path, max_buffered_samples=4096) as reader:
        check = reader.check_frame_rate(RATE_HZ, first_frame_timeout_s=5.0)
    assert check.judged
    assert abs(check.measured_hz / RATE_HZ - 1) <= daq_reader.FRAME_RATE_TOLERANCE, check


def named_rate(error: DaqRateMismatch, expected_hz: float) -> float:
    """The measured rate the message names ("streams 16000 frames/s, 8000 expected"), checked against the
    error's own figures."""
    found = re.search(r"streams (\d+) frames/s, (\d+) expected", str(error))
    assert found, str(error)
    assert float(found[2]) == expected_hz == error.expected_hz, str(error)
    assert abs(float(found[1]) / error.measured_hz - 1) < 0.01, str(error)  # rounded to 3 digits
    return float(found[1])


@pytest.mark.parametrize("true_hz, configured_hz", [(RATE_HZ, RATE_HZ / 2), (RATE_HZ / 2, RATE_HZ)])
def test_a_daq_at_another_rate_is_named_with_both_rates(pty_writer, true_hz, configured_hz):
    paced(pty_writer, true_hz)
    with DaqReader(pty_writer.path, max_buffered_samples=4096) as reader:
        with pytest.raises(DaqRateMismatch) as info:
            reader.check_frame_rate(configured_hz, first_frame_timeout_s=5.0)
    assert abs(named_rate(info.value, configured_hz) / true_hz - 1) <= daq_reader.FRAME_RATE_TOLERANCE


def test_a_stream_as_fast_as_it_is_read_is_not_judged(pty_writer):
    """The emulator at --speedup 0 streams as fast as it is read: the wall clock says nothing of its
    sample clock, so it is neither passed nor refused on it."""
    pty_writer.write_in_thread(frames(60.0))  # far more than the check reads
    with DaqReader(pty_writer.path, max_buffered_samples=4096) as reader:
        check = reader.check_frame_rate(RATE_HZ, first_frame_timeout_s=5.0)
    assert not check.judged
    assert check.measured_hz > daq_reader.FREE_RUNNING_RATIO * RATE_HZ, check


def test_a_port_that_opens_but_streams_nothing_is_named(pty_writer):
    with DaqReader(pty_writer.path) as reader:
        with pytest.raises(DaqNotStreaming, match=r"no frame came within 0.5 s.*is the DAQ streaming"):
            reader.check_frame_rate(RATE_HZ, first_frame_timeout_s=0.5)


@pytest.mark.parametrize(
    "path, what",
    [("regular", "is a regular file"), ("/dev/null", "is a character device that is not a terminal")],
)
def test_a_path_that_cannot_be_a_serial_port_is_named(tmp_path, path, what):
    if path == "regular":
        path = tmp_path / "capture.bin"
        path.write_bytes(frames(0.01))
    reader = DaqReader(str(path))
    with pytest.raises(DaqNotSerialPort, match=f"{what}, not a serial port"):
        reader.start()
