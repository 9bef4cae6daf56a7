"""Real-time factor of the emulated bench, and its paced mode (run: python -m tests.benchmarks.bench_emulator).

Real-time factors, at OP1 of paper-bench (2.5 Nm, 2000 rpm, 12 V) with injection, disturbance map,
saturation, dead time and sensor noise on:
- physics + frames: physics.simulate in blocks of 16 x 256 samples, frames encoded, no pty;
- emulator: the real Emulator plant thread at --speedup 0 (physics + setpoint hand-over + frame
  encoding + blocking pty writes) while a separate `cat` process drains the pty.
Real-time factor = simulated plant time / wall time.

Paced mode (--speedup X > 0, a real DAQ's discipline):
- frames lost: `python -m plant_emulator --speedup X` for X = 1, 5, 10, 20, a DaqReader in this process
  consuming as fast as it can (read_available) for 3 s: frames received against the sequence span
  (expected), the difference lost, and how the reader counted them; the emulator's CPU share (its
  process, all threads, /proc) at 1x with nobody changing setpoints;
- setpoint latency: an in-process Emulator at 1x, setpoints written through its drive firmware while
  a DaqReader consumes: wall time from the write to the consumer holding the sample whose sync
  toggle shows the setpoint took effect.
"""

from __future__ import annotations

import math
import os
import subprocess
import threading
import time

import numpy as np

from drivers.daq_protocol import FLAG_SYNC_INPUT
from drivers.daq_reader import DaqReader
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta
from plant_emulator.process import Emulator, warm_up
from tests.support.bench_rig import EmulatorRig

PACED_SPEEDUPS = (1.0, 5.0, 10.0, 20.0)
CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def physics_factor(seconds: float = 2.0, chunk: int = 256, block_chunks: int = 16) -> float:
    """Full physics (saturation, MTPA/FW, dead time, disturbance map, injection) plus frame encoding,
    in the process's blocks of 16 chunks, one numba call each."""
    p, tab = scn.build(scn.load("paper-bench"))
    plant = ph.Plant(p, tab, chunk=chunk)
    plant.init_op(2.5, 2000.0, 12.0)
    sp = op_setpoints(12.0, 2.5, 2000.0, theta_from_gamma_delta(math.radians(3), math.radians(280)))
    k = chunk * block_chunks
    frames = np.empty(k * ph.FRAME_BYTES, dtype=np.uint8)
    summary = np.zeros((block_chunks, ph.N_SUMMARY))
    no_trace = np.zeros((0, ph.N_TRACE))
    ph.simulate(
        plant.x, p, tab, sp, ph.NO_THETA_SCHEDULE, plant.rng.standard_normal(k), chunk, 0, frames, summary, no_trace
    )
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        ph.simulate(
            plant.x, p, tab, sp, ph.NO_THETA_SCHEDULE, plant.rng.standard_normal(k), chunk, n, frames, summary, no_trace
        )
        frames.tobytes()
        n += k
    return n * p[ph.P_TS] / (time.perf_counter() - t0)


def emulator_factor(seconds: float = 3.0, one_core: bool = False) -> float:
    """one_core: the emulator process is pinned to CPU 0 and the reader (`cat`, standing in for the
    service's DAQ reader, a separate process on a bench PC) to CPU 1."""
    import os

    previous = os.sched_getaffinity(0)
    if one_core:
        os.sched_setaffinity(0, {0})
    emu = Emulator(scn.load("paper-bench"), speedup=0.0)
    # put the plant at OP1 with injection, as the firmware would after the service's setpoints
    ph.steady_state_init(emu.plant.x, emu.params, 2.5, 2000.0, 12.0)
    emu.supply.set_output(True)
    from drivers.cia402 import State402

    emu.drive.state = State402.OPERATION_ENABLED
    emu.load.state = State402.OPERATION_ENABLED
    emu.load.store(0x60FF, 0, 2000)
    emu.drive.torque_nm = 2.5
    emu.drive.inj_mode = 1
    emu.drive.theta = theta_from_gamma_delta(math.radians(3), math.radians(280))
    pin = "taskset -c 1 " if one_core and len(previous) > 1 else ""
    reader = subprocess.Popen(["sh", "-c", f"exec {pin}cat {emu.daq.name} > /dev/null 2>&1"])
    try:
        emu.start()
        time.sleep(0.5)
        s0, t0 = emu.samples, time.perf_counter()
        time.sleep(seconds)
        s1, t1 = emu.samples, time.perf_counter()
    finally:
        emu.close()
        reader.kill()
        reader.wait()
        os.sched_setaffinity(0, previous)
    return (s1 - s0) / emu.sample_rate_hz / (t1 - t0)


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process, all its threads (/proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_PER_S


def paced_loss(speedup: float, seconds: float = 3.0) -> dict:
    """`python -m plant_emulator --speedup X` read by a DaqReader consuming as fast as it can."""
    rig = EmulatorRig(speedup=speedup)
    try:
        with DaqReader(rig.endpoints["daq"]) as reader:
            warm_until = time.monotonic() + 0.5
            while time.monotonic() < warm_until:  # past the start (pyserial's open flushes)
                reader.read_available(1 << 16, timeout_s=5.0)
            c0, cpu0, t0 = reader.counters, process_cpu_s(rig.proc.pid), time.monotonic()
            first = last = None
            got = 0
            while time.monotonic() - t0 < seconds:
                block = reader.read_available(1 << 16, timeout_s=5.0)
                first = int(block.index[0]) if first is None else first
                last = int(block.index[-1])
                got += len(block)
            cpu1, t1, c1 = process_cpu_s(rig.proc.pid), time.monotonic(), reader.counters
    finally:
        rig.stop()
    expected = last - first + 1
    return {
        "speedup": speedup,
        "expected": expected,
        "received": got,
        "lost": expected - got,
        "rate_x": got / (t1 - t0) / 16000.0,
        "cpu": (cpu1 - cpu0) / (t1 - t0),
        "sequence_gaps": c1.sequence_gaps - c0.sequence_gaps,
        "overruns": c1.overruns - c0.overruns,
    }


def setpoint_latency_ms(writes: int = 20) -> list[float]:
    """In-process Emulator at 1x: ms from a setpoint write (drive firmware, as the SDO server does) to
    the consumer holding the sample whose sync toggle shows it took effect."""
    emu = Emulator(scn.load("paper-bench"), speedup=1.0)
    emu.start()
    toggles_at: list[float] = []
    stop = threading.Event()
    try:
        with DaqReader(emu.daq.name) as reader:
            level = None

            def consume():
                nonlocal level
                while not stop.is_set():
                    block = reader.read_available(1 << 16, timeout_s=5.0)
                    now = time.monotonic()
                    lv = (block.flags & FLAG_SYNC_INPUT) != 0
                    level = bool(lv[0]) if level is None else level
                    toggles_at.extend([now] * int(np.count_nonzero(lv != np.concatenate([[level], lv[:-1]]))))
                    level = bool(lv[-1])

            consumer = threading.Thread(target=consume, daemon=True)
            consumer.start()
            time.sleep(0.3)
            written_at = []
            for k in range(writes):
                written_at.append(time.monotonic())
                emu.drive.write_object(0x2000, 6, (k + 1) % 2)  # decoupling on/off: one event each
                time.sleep(0.05)
            time.sleep(0.2)
            stop.set()
            consumer.join(6.0)
    finally:
        emu.close()
    return [(t - w) * 1e3 for w, t in zip(written_at, toggles_at)]


def main() -> None:
    warm_up()
    print(f"physics + frame encoding real-time factor (no pty): {physics_factor():.0f}")
    print(f"emulator real-time factor (physics + DAQ encode + pty): {emulator_factor():.0f}")
    print(
        f"emulator real-time factor, emulator pinned to one core (reader on the other): "
        f"{emulator_factor(one_core=True):.0f}"
    )
    print("paced (--speedup X, python -m plant_emulator), a DaqReader consuming as fast as it can for 3 s:")
    for speedup in PACED_SPEEDUPS:
        r = paced_loss(speedup)
        print(
            f"  {speedup:4g}x: frames received {r['received']} of {r['expected']} expected, dropped {r['lost']} "
            f"({r['lost'] / r['expected']:.2%}; reader: {r['sequence_gaps']} sequence gaps, {r['overruns']} "
            f"overruns), {r['rate_x']:.2f}x real time, emulator CPU {r['cpu']:.0%} of a core"
        )
        if speedup == 1.0:
            idle_cpu = r["cpu"]
    print(f"emulator CPU at 1x idle (nobody changing setpoints, the DAQ read): {idle_cpu:.1%} of a core")
    lat = setpoint_latency_ms()
    print(
        f"setpoint write -> its sync toggle in the consumer's hands at 1x (in-process, {len(lat)} writes): "
        f"p50 {np.percentile(lat, 50):.1f} ms, max {max(lat):.1f} ms"
    )


if __name__ == "__main__":
    main()
