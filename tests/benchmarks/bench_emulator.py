"""Real-time factor of the emulated bench (run: python -m tests.benchmarks.bench_emulator).

Two numbers, both at OP1 of paper-bench (2.5 Nm, 2000 rpm, 12 V) with injection, disturbance map,
saturation, dead time and sensor noise on:
- physics + frames: physics.simulate in blocks of 16 x 256 samples, frames encoded, no pty;
- emulator: the real Emulator plant thread at --speedup 0 (physics + setpoint hand-over + frame
  encoding + blocking pty writes) while a separate `cat` process drains the pty.
Real-time factor = simulated plant time / wall time.
"""
from __future__ import annotations

import math
import subprocess
import time


import numpy as np

from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta
from plant_emulator.process import Emulator, warm_up


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
    ph.simulate(plant.x, p, tab, sp, plant.rng.standard_normal(k), chunk, 0, frames, summary, no_trace)
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        ph.simulate(plant.x, p, tab, sp, plant.rng.standard_normal(k), chunk, n, frames, summary, no_trace)
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


def main() -> None:
    warm_up()
    print(f"physics + frame encoding real-time factor (no pty): {physics_factor():.0f}")
    print(f"emulator real-time factor (physics + DAQ encode + pty): {emulator_factor():.0f}")
    print(f"emulator real-time factor, emulator pinned to one core (reader on the other): "
          f"{emulator_factor(one_core=True):.0f}")


if __name__ == "__main__":
    main()
