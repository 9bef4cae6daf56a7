"""DAQ decoding + demodulation throughput on one core (run: python -m tests.benchmarks.bench_daq).

Frames of DESIGN section 5 are encoded once, then decoded by drivers.daq_protocol.FrameDecoder in
64 KiB chunks (what the reader thread gets from the port) and demodulated into h-th phasors over
whole-period windows (service.harmonic.phasor). Throughput = samples / wall time of decode+demod.
"""
from __future__ import annotations

import math
import time


import numpy as np

from drivers.daq_protocol import FrameDecoder, encode_frames
from service.harmonic import phasor

N = 2_000_000
FS, H = 16000.0, 6
W_E = 2000 / 60 * 2 * math.pi * 4


def main() -> None:
    k = np.arange(N)
    angle = (W_E * k / FS) % (2 * math.pi)
    alpha = 0.07 * np.cos(H * angle + 1.0) + 1e-3 * np.random.default_rng(0).standard_normal(N)
    data = encode_frames(k & 0xFFFF, np.round(angle / (2 * math.pi) * 65536).astype(np.int64) & 0xFFFF,
                         np.round(alpha * 32767).astype(np.int16), np.zeros(N, np.uint16))
    chunk = 65536
    best = 0.0
    for _ in range(3):
        dec = FrameDecoder()
        t0 = time.perf_counter()
        decoded = 0
        phasors = 0
        for i in range(0, len(data), chunk):
            s = dec.feed(data[i:i + chunk])
            decoded += len(s)
            if len(s) > 200:
                phasor(s.accel_fs, s.angle_rad, H, 6)   # whole electrical turn windows
                phasors += 1
        dt = time.perf_counter() - t0
        best = max(best, decoded / dt)
    assert decoded == N, decoded
    print(f"DAQ decode + demodulation throughput (one core, 64 KiB chunks): {best / 1e6:.2f} million samples/s")


if __name__ == "__main__":
    main()
