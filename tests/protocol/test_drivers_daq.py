"""DaqReader against a real pty (the emulator's transport) and a loopback TCP socket, no mocks.

Frames are made with drivers.daq_protocol.encode_frames, the encoder the emulator uses, and written to
the pty master by a writer thread; the reader opens the slave by its /dev/pts path like any serial port.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest

from drivers import daq_protocol, daq_reader
from drivers.daq_protocol import FLAG_SENSOR_FAULT, FLAG_SYNC_INPUT, FRAME_BYTES, encode_frames
from drivers.daq_reader import DaqDisconnected, DaqPortBusy, DaqReader, DaqTimeout
from tests.support.pty_writer import PtyWriter
from tests.support.waiting import wait_until


def make_stream(n: int, first_seq: int = 0, seed: int = 1) -> tuple[bytes, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    seq = first_seq + np.arange(n)
    angle = (np.arange(n) * 977) % 65536
    accel = rng.integers(-32767, 32768, n)
    flags = np.where(np.arange(n) % 50 == 0, FLAG_SYNC_INPUT, 0)
    flags[n // 3] |= FLAG_SENSOR_FAULT
    return encode_frames(seq, angle, accel, flags), {"angle": angle, "accel": accel, "flags": flags}


@pytest.fixture
def pty_writer():
    writer = PtyWriter()
    yield writer
    writer.close()


def test_samples_arrive_in_order_with_values(pty_writer):
    n = 6000
    stream, truth = make_stream(n, first_seq=65536 - 1000)  # crosses the 16-bit sequence wrap
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write_in_thread(stream, piece_bytes=1000)  # pieces cut frames in half
        first = reader.read(1234, timeout_s=5.0)
        rest = reader.read(n - 1234, timeout_s=5.0)
    assert len(first) == 1234 and len(rest) == n - 1234
    index = np.concatenate([first.index, rest.index])
    np.testing.assert_array_equal(index, np.arange(n))
    angle = np.concatenate([first.angle_rad, rest.angle_rad])
    np.testing.assert_allclose(angle, truth["angle"] * 2 * math.pi / 65536)
    accel = np.concatenate([first.accel_fs, rest.accel_fs])
    np.testing.assert_allclose(accel, truth["accel"] / 32767)
    np.testing.assert_array_equal(np.concatenate([first.flags, rest.flags]), truth["flags"])
    assert not first.gap_before.any() and not rest.gap_before.any()
    assert reader.counters.frames == n and reader.counters.crc_failures == 0


def test_corrupted_frame_and_dropped_bytes_are_counted_and_marked(pty_writer):
    n = 1000
    stream, _ = make_stream(n)
    data = bytearray(stream)
    data[100 * FRAME_BYTES + 5] ^= 0xFF  # frame 100: bad CRC
    del data[300 * FRAME_BYTES + 3 : 300 * FRAME_BYTES + 8]  # frame 300: five bytes lost
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write_in_thread(bytes(data))
        samples = reader.read(n - 2, timeout_s=5.0)
        counters = reader.counters
    expected_index = np.delete(np.arange(n), [100, 300])
    np.testing.assert_array_equal(samples.index, expected_index)
    np.testing.assert_array_equal(np.flatnonzero(samples.gap_before), [100, 299])  # samples 101 and 301
    assert counters.crc_failures >= 1
    assert counters.sequence_gaps == 2
    assert counters.samples_lost == 2
    assert counters.bytes_skipped > 0


def test_backpressure_reader_stops_reading_until_consumed(pty_writer):
    n = 200_000  # 2.4 MB, far more than the pty buffers
    max_buffered = 500
    stream, _ = make_stream(n)
    with DaqReader(pty_writer.path, max_buffered_samples=max_buffered, read_chunk_bytes=1200) as reader:
        writer = pty_writer.write_in_thread(stream)
        time.sleep(0.5)
        written_early = pty_writer.bytes_written
        time.sleep(0.3)
        # nobody consumes: the queue is full, the reader has stopped, so the writer is blocked
        assert writer.is_alive()
        assert pty_writer.bytes_written == written_early
        assert reader.buffered_samples <= max_buffered
        assert reader.bytes_read <= (max_buffered + 1) * FRAME_BYTES
        assert pty_writer.bytes_written < len(stream) // 10
        # consuming lets the stream flow again, without loss
        next_index = 0
        while next_index < n:
            block = reader.read(min(4000, n - next_index), timeout_s=5.0)
            assert block.index[0] == next_index and not block.gap_before.any()
            next_index = int(block.index[-1]) + 1
        writer.join(5.0)
        assert pty_writer.bytes_written == len(stream)
        assert reader.counters.frames == n


def test_read_larger_than_buffer_limit_completes(pty_writer):
    stream, _ = make_stream(3000)
    with DaqReader(pty_writer.path, max_buffered_samples=256) as reader:
        pty_writer.write_in_thread(stream)
        samples = reader.read(3000, timeout_s=5.0)
    np.testing.assert_array_equal(samples.index, np.arange(3000))


def test_timeout_says_how_many_arrived_and_keeps_them(pty_writer):
    stream, _ = make_stream(100)
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write_in_thread(stream).join(2.0)
        deadline = time.monotonic() + 10.0  # the reader's thread may lag under load: all 100 in first
        while reader.buffered_samples < 100 and time.monotonic() < deadline:
            time.sleep(0.01)
        t0 = time.monotonic()
        with pytest.raises(DaqTimeout, match="only 100 of 200 samples arrived within 0.3 s"):
            reader.read(200, timeout_s=0.3)
        assert 0.25 < time.monotonic() - t0 < 5.0
        samples = reader.read(100, timeout_s=1.0)  # nothing was lost by the timeout
    np.testing.assert_array_equal(samples.index, np.arange(100))


def test_disconnect_when_the_master_closes(pty_writer):
    stream, _ = make_stream(50)
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write_in_thread(stream).join(2.0)
        assert len(reader.read(50, timeout_s=2.0)) == 50
        pty_writer.close_master()
        t0 = time.monotonic()
        with pytest.raises(DaqDisconnected, match="disconnected"):
            reader.read(10, timeout_s=5.0)
        assert time.monotonic() - t0 < 2.0  # reported at once, not after the timeout
        assert reader.error is not None


def test_read_before_start_is_an_error():
    reader = DaqReader("loop://")
    with pytest.raises(DaqDisconnected, match="not started"):
        reader.read(1, timeout_s=0.1)


def test_a_million_samples_over_tcp_arrive_in_order():
    """Large chunks over loopback TCP: every sample arrives, in order, none twice. (Its speed is a
    figure of `make bench` (tests/benchmarks/bench_daq.py), never a timed assertion here.)"""
    n = 1_000_000
    stream, _ = make_stream(n)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve():
        conn, _ = server.accept()
        with conn:
            time.sleep(0.2)  # pyserial's socket:// open() discards whatever arrived before it finished
            conn.sendall(stream)
            time.sleep(1.0)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        with DaqReader(f"socket://127.0.0.1:{port}", max_buffered_samples=1 << 18, read_chunk_bytes=1 << 18) as reader:
            first = reader.read(1, timeout_s=5.0)
            got = 1
            last = int(first.index[0])
            while got < n:
                block = reader.read(min(1 << 16, n - got), timeout_s=5.0)
                assert block.index[0] == last + 1
                last = int(block.index[-1])
                got += len(block)
            assert reader.counters.sequence_gaps == 0 and reader.counters.crc_failures == 0
    finally:
        server.close()
        thread.join(3.0)
    assert got == n and last == int(first.index[0]) + n - 1


def read_exactly(reader: DaqReader, n: int, timeout_s: float = 5.0):
    """n samples by read_available (each call returns at least one): what a consumer that confirms
    a setpoint as soon as it arrives does."""
    blocks, got = [], 0
    while got < n:
        block = reader.read_available(n - got, timeout_s)
        assert 1 <= len(block) <= n - got
        blocks.append(block)
        got += len(block)
    return blocks


def test_small_writes_are_handed_over_without_waiting_for_a_full_chunk(pty_writer, monkeypatch):
    # a first-byte wait of a minute: a reader that waited for a full chunk (or its timeout) before
    # handing over would hold each 10-frame write for that minute, and every read below would time out
    monkeypatch.setattr(daq_reader, "SERIAL_READ_TIMEOUT_S", 60.0)
    stream, _ = make_stream(50)
    with DaqReader(pty_writer.path) as reader:
        for k in range(5):
            pty_writer.write(stream[k * 10 * FRAME_BYTES : (k + 1) * 10 * FRAME_BYTES])
            blocks = read_exactly(reader, 10)
            index = np.concatenate([b.index for b in blocks])
            np.testing.assert_array_equal(index, np.arange(k * 10, (k + 1) * 10))
    assert reader.counters.frames == 50


def test_read_available_returns_what_is_there_and_at_most_max_n(pty_writer):
    stream, _ = make_stream(100)
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write(stream[: 10 * FRAME_BYTES])
        wait_until(lambda: reader.buffered_samples == 10, 10.0, "10 samples queued")
        ten = reader.read_available(1000, timeout_s=5.0)  # the 10 there, without waiting for 1000
        np.testing.assert_array_equal(ten.index, np.arange(10))
        pty_writer.write(stream[10 * FRAME_BYTES :])
        wait_until(lambda: reader.buffered_samples == 90, 10.0, "90 samples queued")
        first = reader.read_available(30, timeout_s=5.0)
        rest = reader.read_available(1000, timeout_s=5.0)
        np.testing.assert_array_equal(first.index, np.arange(10, 40))
        np.testing.assert_array_equal(rest.index, np.arange(40, 100))
        with pytest.raises(DaqTimeout, match="no sample arrived within 0.2 s"):
            reader.read_available(1000, timeout_s=0.2)
        with pytest.raises(ValueError):
            reader.read_available(0, timeout_s=1.0)
        pty_writer.close_master()
        with pytest.raises(DaqDisconnected, match="disconnected"):
            reader.read_available(10, timeout_s=5.0)


def test_a_flush_is_counted_as_the_flushs_not_as_line_errors(pty_writer):
    n, skipped = 200, 37
    stream, _ = make_stream(1000)
    with DaqReader(pty_writer.path, max_buffered_samples=n) as reader:
        # n frames fill the queue (the thread pauses), the next ones and half a frame wait in the OS
        pty_writer.write(stream[: (n + 50) * FRAME_BYTES + 5])
        wait_until(lambda: reader.buffered_samples == n, 10.0, "the queue full")
        assert reader.discard_buffered(flush_port=True) == n
        # the DAQ goes on mid-frame: the rest of a frame, then whole ones (frames between were flushed)
        resume = n + 50 + skipped
        pty_writer.write(stream[resume * FRAME_BYTES + 5 : (resume + 100) * FRAME_BYTES])
        after = reader.read(99, timeout_s=5.0)
        counters, health = reader.counters, reader.health()
    np.testing.assert_array_equal(after.index, np.arange(resume + 1, resume + 100))
    assert after.gap_before[0] and not after.gap_before[1:].any()  # the stream has a hole there
    assert (counters.crc_failures, counters.sequence_gaps, counters.samples_lost) == (0, 0, 0)
    assert (counters.bytes_skipped, counters.resyncs) == (0, 0)
    # the rest of the cut frame at least; a read the thread had in hand when it paused may add a partial
    # frame of its own (it depends on where the OS cut the reads), never a whole frame
    assert counters.flush_resyncs == 1 and FRAME_BYTES - 5 <= counters.flush_bytes_skipped < 2 * FRAME_BYTES
    assert counters.flush_samples_lost == resume + 1 - n
    assert health["flushes"] == 1 and health["flush_resyncs"] == 1 and health["sequence_gaps"] == 0


def test_whole_frames_missing_after_a_backpressure_pause_are_an_overrun(pty_writer, monkeypatch):
    n = 300
    stream, _ = make_stream(2000)
    frame = lambda k: stream[k * FRAME_BYTES : (k + 1) * FRAME_BYTES]  # noqa: E731
    # an overrun window of 50 frames (instead of 256 KiB), so that this short stream can leave the one
    # that follows the reader's start (the port's backlog) before its hole
    monkeypatch.setattr(daq_protocol, "OVERRUN_WINDOW_BYTES", 50 * FRAME_BYTES)
    with DaqReader(pty_writer.path, max_buffered_samples=n) as reader:
        pty_writer.write(stream[: 100 * FRAME_BYTES])
        wait_until(lambda: reader.buffered_samples == 100, 10.0, "the start's window read")
        # outside every window, whole frames missing (100..102) are a sequence gap: no known cause
        pty_writer.write(b"".join(frame(k) for k in range(103, n + 3)))
        wait_until(lambda: reader.buffered_samples == n, 10.0, "the queue full")
        # nobody consumes: the reader pauses, a DAQ streaming on overflows and drops frames n+3..n+499
        pty_writer.write(b"".join(frame(k) for k in range(n + 500, n + 700)))
        before = reader.read(n, timeout_s=5.0)
        after = reader.read(200, timeout_s=5.0)
        counters, health = reader.counters, reader.health()
    assert np.flatnonzero(before.gap_before).tolist() == [100]
    np.testing.assert_array_equal(after.index, np.arange(n + 500, n + 700))
    assert after.gap_before[0] and not after.gap_before[1:].any()
    assert counters.sequence_gaps == 1 and counters.samples_lost == 3
    assert counters.overruns == 1 and counters.overrun_samples_lost == 497
    assert counters.crc_failures == 0
    assert health["overruns"] == 1 and health["overrun_samples_lost"] == 497


def test_whole_frames_missing_in_the_backlog_a_reader_finds_at_start_are_an_overrun(pty_writer):
    """A DAQ streams before anybody reads it (the emulator at --speedup 0 falls back to real time and
    drops frames): the hole in what the reader finds at its start is the DAQ's overflow, not a line error."""
    stream, _ = make_stream(1000)
    with DaqReader(pty_writer.path) as reader:
        pty_writer.write(stream[: 400 * FRAME_BYTES] + stream[700 * FRAME_BYTES :])
        samples = reader.read(700, timeout_s=5.0)
        counters = reader.counters
    assert np.flatnonzero(samples.gap_before).tolist() == [400] and samples.index[400] == 700
    assert (counters.sequence_gaps, counters.samples_lost, counters.crc_failures) == (0, 0, 0)
    assert counters.overruns == 1 and counters.overrun_samples_lost == 300


def test_a_second_reader_of_one_port_is_refused_naming_it(pty_writer, tmp_path):
    stream, _ = make_stream(2000)
    link = tmp_path / "usb-ripplecal_emulated_DAQ-if00"  # a stable path, as the emulator and udev make
    link.symlink_to(pty_writer.path)
    with DaqReader(str(link)) as first:
        for url in (pty_writer.path, str(link)):  # the device, by either of its names
            second = DaqReader(url)
            with pytest.raises(DaqPortBusy, match=rf"DAQ {url}: another process holds this port") as info:
                second.start()
            assert "one reader per DAQ" in str(info.value)
            assert not second.running
        # the first reader keeps the whole stream
        pty_writer.write_in_thread(stream)
        samples = first.read(2000, timeout_s=5.0)
        np.testing.assert_array_equal(samples.index, np.arange(2000))
    # once it let go, the port is free for the next one
    with DaqReader(pty_writer.path) as again:
        assert again.connected
