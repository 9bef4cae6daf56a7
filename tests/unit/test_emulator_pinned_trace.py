"""simulate() pinned against a trace recorded before physics.py became a package of stages.

The restructuring moved code, not numbers: four short runs that together pass through every stage
and branch of the control-period loop (injection by rotation and by the eq. 11 estimate,
decoupling, field weakening, dead time, saturation tables, disturbance map with h != injection
order, power stage off, load ramp, over-range clipping, sync flag) must give the recorded traces,
final states and per-chunk summaries to float rounding, and the recorded DAQ frame bytes exactly.
The recording is tests/data/physics_trace_pinned.json (written by `record()` from the code at
commit e535cf8, before the split). Deliberate physics changes since, each recorded again: the
disturbance harmonic became the currents' (none with the power stage off); the dead-time error became
the exact period mean along the phase currents' own path (inverter.dead_time_voltage: the former
band assumed the fundamental's slope, so the 6th harmonic depended on where the zero crossings fell on
the sample grid, a phase a speed with whole samples per turn latched for a whole run); the current
PI's anti-windup became back-calculation (fw_vest_decoupled_h12 saturates: conditional integration
froze the integrators for as long as the limit held, so at a point the true machine cannot reach the
voltage angle, the currents and the harmonic kept the run's history); the disturbance's 2h part tied to
the h-th by a ratio gave way to further harmonics with maps of their own (paper-bench: a 12th; checked in
closed form by test_emulator_truth.py test_each_torque_harmonic_is_its_own_map; the two cases without
the map's tables stayed as recorded).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.calibrate_paper_bench import op_setpoints, theta_from_gamma_delta

PINNED = Path(__file__).resolve().parents[1] / "data" / "physics_trace_pinned.json"
TRACE_EVERY = 7  # every 7th sample of the per-sample trace is kept in the recording


def _run(x, p, tab, sp, n, chunk, seq0, noise_seed):
    noise = np.random.default_rng(noise_seed).standard_normal(n)
    frames = np.zeros(n * ph.FRAME_BYTES, dtype=np.uint8)
    summary = np.zeros((-(-n // chunk), ph.N_SUMMARY))
    trace = np.zeros((n, ph.N_TRACE))
    ph.simulate(
        x, p, tab, np.asarray(sp, dtype=np.float64), ph.NO_THETA_SCHEDULE, noise, chunk, seq0, frames, summary, trace
    )
    return {
        "trace": trace[::TRACE_EVERY].tolist(),
        "state": x.tolist(),
        "summary": summary.tolist(),
        "frames_sha256": hashlib.sha256(frames.tobytes()).hexdigest(),
    }


def run_cases() -> dict:
    """The four pinned runs (each a list of consecutive calls on one state)."""
    p, tab = scn.build(scn.load("paper-bench"))
    out = {}

    # 1. OP1 with the paper's injection (rotation), saturation, disturbance map, dead time, noise;
    #    then a call of a length that is not a whole number of chunks with the sync level raised.
    x = ph.new_state()
    ph.steady_state_init(x, p, 2.5, 2000.0, 12.0, tab)
    sp = op_setpoints(12.0, 2.5, 2000.0, theta_from_gamma_delta(math.radians(3), math.radians(280)))
    first = _run(x, p, tab, sp, 1024, 256, 0, 1)
    sp[ph.S_SYNC] = 1.0
    out["op1_injection"] = [first, _run(x, p, tab, sp, 300, 256, 1024, 2)]

    # 2. field weakening (closed loop), eq. 11 estimate, decoupling, injection at h = 12 while the
    #    disturbance is at h = 6
    x = ph.new_state()
    ph.steady_state_init(x, p, 4.0, 3500.0, 12.0, tab)
    sp = op_setpoints(12.0, 4.0, 3500.0, (0.03, -0.02), h=12)
    sp[ph.S_DECOUPLING] = 1.0
    sp[ph.S_VEST] = 1.0
    out["fw_vest_decoupled_h12"] = [_run(x, p, tab, sp, 768, 256, 65000, 3)]

    # 3. power stage off while the load machine ramps the shaft down to 1000 rpm
    x = ph.new_state()
    ph.steady_state_init(x, p, 2.5, 2000.0, 12.0, tab)
    sp = op_setpoints(12.0, 2.5, 1000.0)
    sp[ph.S_POWER] = 0.0
    out["power_off_load_ramp"] = [_run(x, p, tab, sp, 512, 256, 7, 4)]

    # 4. no tables (unsaturated, no map), no angle compensation, a torque step, a sensor full scale
    #    small enough to clip (over-range flags), chunk 128
    q = p.copy()
    q[ph.P_SAT_N] = q[ph.P_DMAP_NT] = q[ph.P_DMAP_NN] = 0.0
    q[ph.P_ALPHA_FS] = 50.0
    q[ph.P_ANGLE_COMP] = 0.0
    no_tab = np.zeros(1)
    x = ph.new_state()
    ph.steady_state_init(x, q, 0.0, 1500.0, 12.0)
    sp = op_setpoints(12.0, 3.0, 1500.0)
    out["no_tables_over_range"] = [_run(x, q, no_tab, sp, 600, 128, 0, 5)]
    return out


def record() -> None:
    """Write the recording (run once, before the change being checked)."""
    PINNED.parent.mkdir(exist_ok=True)
    PINNED.write_text(json.dumps(run_cases(), indent=0) + "\n")


@pytest.fixture(scope="module")
def runs():
    return run_cases(), json.loads(PINNED.read_text())


@pytest.mark.parametrize(
    "case", ["op1_injection", "fw_vest_decoupled_h12", "power_off_load_ramp", "no_tables_over_range"]
)
def test_simulate_reproduces_the_trace_recorded_before_the_split(runs, case):
    got, pinned = runs
    assert len(got[case]) == len(pinned[case])
    for now, before in zip(got[case], pinned[case]):
        for key in ("trace", "state", "summary"):
            a, b = np.asarray(now[key]), np.asarray(before[key])
            scale = np.maximum(np.max(np.abs(b), axis=0), 1e-300) if b.ndim > 1 else np.abs(b) + 1e-300
            assert np.all(np.abs(a - b) <= 1e-12 * scale), (
                f"{case} {key}: max rel. deviation {np.max(np.abs(a - b) / scale):.3g}"
            )
        assert now["frames_sha256"] == before["frames_sha256"], f"{case}: DAQ frame bytes changed"
