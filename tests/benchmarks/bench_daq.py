"""DAQ decoding + demodulation throughput on one core, and the reader's latency in real time
(run: python -m tests.benchmarks.bench_daq).

Throughput: frames of docs/interfaces.md ("DAQ stream frame") are encoded once, then decoded by
drivers.daq_protocol.FrameDecoder in 64 KiB chunks (a backlog as the reader thread gets it from the
port) and demodulated into h-th phasors over whole-period windows (service.model.harmonic.phasor).
Throughput = samples / wall time of decode+demod.

Latency: a writer thread streams frames into a real pty at 16 kHz on the wall clock, 1 ms of frames
(16) per write, as a DAQ does, timestamping each write; a DaqReader reads the slave and a consumer
takes samples with read_available as soon as they are there. Latency of a write = the time the
consumer holds its last sample minus the time the write returned.
"""

from __future__ import annotations

import math
import time

import numpy as np

from drivers.daq_protocol import FRAME_BYTES, FrameDecoder, encode_frames
from drivers.daq_reader import DaqReader
from service.model.harmonic import phasor
from tests.support.pty_writer import PtyWriter

N = 2_000_000
FS, H = 16000.0, 6
W_E = 2000 / 60 * 2 * math.pi * 4
LATENCY_S = 3.0
PACKET_SAMPLES = 16  # 1 ms at 16 kHz


def encoded(n: int) -> bytes:
    k = np.arange(n)
    angle = (W_E * k / FS) % (2 * math.pi)
    alpha = 0.07 * np.cos(H * angle + 1.0) + 1e-3 * np.random.default_rng(0).standard_normal(n)
    return encode_frames(
        k & 0xFFFF,
        np.round(angle / (2 * math.pi) * 65536).astype(np.int64) & 0xFFFF,
        np.round(alpha * 32767).astype(np.int16),
        np.zeros(n, np.uint16),
    )


def throughput() -> float:
    data = encoded(N)
    chunk = 65536
    best = 0.0
    for _ in range(3):
        dec = FrameDecoder()
        t0 = time.perf_counter()
        decoded = 0
        for i in range(0, len(data), chunk):
            s = dec.feed(data[i : i + chunk])
            decoded += len(s)
            if len(s) > 200:
                phasor(s.accel_fs, s.angle_rad, H, 6)  # whole electrical turn windows
        dt = time.perf_counter() - t0
        best = max(best, decoded / dt)
    assert decoded == N, decoded
    return best


def reader_latency_ms() -> np.ndarray:
    """Per 1 ms write at 16 kHz real time: ms from the write to the consumer holding its last sample."""
    n = int(LATENCY_S * FS)
    data = encoded(n)
    writer = PtyWriter()
    held_at = np.full(n, np.nan)  # when the consumer got each sample
    try:
        with DaqReader(writer.path) as reader:
            thread = writer.write_at_rate(data, PACKET_SAMPLES * FRAME_BYTES, FS * FRAME_BYTES)
            got = 0
            while got < n:
                block = reader.read_available(n - got, timeout_s=5.0)
                held_at[block.index] = time.monotonic()
                got += len(block)
            thread.join(5.0)
    finally:
        writer.close()
    last_of_packet = np.arange(PACKET_SAMPLES - 1, n, PACKET_SAMPLES)
    return (held_at[last_of_packet] - np.asarray(writer.piece_times)) * 1e3


def main() -> None:
    print(f"DAQ decode + demodulation throughput (one core, 64 KiB chunks): {throughput() / 1e6:.2f} million samples/s")
    lat = reader_latency_ms()
    print(
        f"DAQ reader latency at 16 kHz real time (1 ms writes into a pty, consumer on read_available, "
        f"{len(lat)} writes): p50 {np.percentile(lat, 50):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, "
        f"max {lat.max():.2f} ms"
    )


if __name__ == "__main__":
    main()
