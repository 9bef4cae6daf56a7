"""Real-time factor of the emulated bench (run: python tests/benchmarks/bench_emulator.py).

Two numbers, both at OP1 of paper-bench (2.5 Nm, 2000 rpm, 12 V) with injection and disturbance on:
- physics only: simulate_chunk in chunks of 256 samples, no frames;
- emulator: the real Emulator plant thread at --speedup 0 (physics + setpoint hand-over + frame
  encoding + blocking pty writes) while a separate `cat` process drains the pty.
Real-time factor = simulated plant time / wall time.
"""
from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from plant_emulator import physics as ph  # noqa: E402
from plant_emulator import scenario as scn  # noqa: E402
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta  # noqa: E402
from plant_emulator.process import Emulator, warm_up  # noqa: E402


def physics_factor(seconds: float = 2.0, chunk: int = 256) -> float:
    p = scn.build_params(scn.load("paper-bench"))
    plant = ph.Plant(p)
    ph.steady_state_init(plant.x, p, 2.5, 2000.0, 12.0)
    sp = op_setpoints(12.0, 2.5, 2000.0, theta_from_gamma_delta(math.radians(3), math.radians(280)))
    plant.run(sp, chunk)
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        plant.run(sp, chunk)
        n += chunk
    return n / p[ph.P_TS] ** -1 / (time.perf_counter() - t0)


def emulator_factor(seconds: float = 3.0) -> float:
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
    reader = subprocess.Popen(["sh", "-c", f"exec cat {emu.daq.name} > /dev/null 2>&1"])
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
    return (s1 - s0) / emu.sample_rate_hz / (t1 - t0)


def main() -> None:
    warm_up()
    print(f"physics-only real-time factor: {physics_factor():.0f}")
    print(f"emulator real-time factor (physics + DAQ encode + pty): {emulator_factor():.0f}")


if __name__ == "__main__":
    main()
