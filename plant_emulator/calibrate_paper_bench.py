"""Calibrate the paper-bench disturbance map so that the optimum at OP1 is the paper's.

Paper section 3, Fig. 8: at OP1 = {2.5 Nm, 2000 rpm} (U_dc = 12 V) the 6th harmonic of the
angular acceleration is minimal for gamma = 3 deg, delta = 280 deg. With docs/conventions.md
(Injection and theta), theta* = gamma (cos delta, -sin delta) (eq. 21-22 inverted). The optimal injection cancels every
h-th torque harmonic, so the disturbance d at OP1 must equal minus the h-th harmonic of T_em that
theta* and everything else (dead time, saturation) produce without d:

1. simulate OP1 with theta* applied, ALL effects on and the map scaled to 0; h-th phasor of T_em:
   T_c = (2/N) sum T_em cos(h phi_e), T_s = (2/N) sum T_em sin(h phi_e) over whole periods;
2. d = D cos(h phi_e + phi_D) has the phasor (D cos phi_D, -D sin phi_D) = -(T_c, T_s), so
   D = |T|, phi_D = atan2(T_s, -T_c);
3. the map over (T*, n) is D(OP1) * (0.3 + 0.7 (T*/2.5 Nm)^2) * (0.9 + 0.1 n/2000 rpm) and
   phi_D(OP1) + 12 deg (T* - 2.5 Nm)/2.5 Nm - 8 deg (n - 2000 rpm)/1000 rpm (a plausible smooth
   saturation harmonic: growing with load, turning with load and speed); OP1 is a map node;
4. a few fixed-point passes with d in place remove the (tiny) coupling of d back into the currents.

Run `python -m plant_emulator.calibrate_paper_bench [--write]`; --write puts the map into
scenarios/paper-bench.toml. It also prints the suppression of the alpha harmonic with theta*.
"""

from __future__ import annotations

import argparse
import math
import re

import numpy as np

from . import physics as ph
from . import scenario as scn

OP1_TORQUE_NM = 2.5
OP1_SPEED_RPM = 2000.0
OP1_UDC_V = 12.0
GAMMA_DEG = 3.0
DELTA_DEG = 280.0


def theta_from_gamma_delta(gamma_rad: float, delta_rad: float) -> tuple[float, float]:
    """Inverse of eq. 21-22: theta = gamma (cos delta, -sin delta)."""
    return gamma_rad * math.cos(delta_rad), -gamma_rad * math.sin(delta_rad)


def harmonic_phasor(signal: np.ndarray, phi_e: np.ndarray, h: float) -> tuple[float, float]:
    """(a_c, a_s) = (2/N) sum(signal cos(h phi_e)), (2/N) sum(signal sin(h phi_e)) (docs/conventions.md, Phasors)."""
    n = len(signal)
    return (2.0 / n * float(np.sum(signal * np.cos(h * phi_e))), 2.0 / n * float(np.sum(signal * np.sin(h * phi_e))))


def op_setpoints(udc_v: float, torque_nm: float, speed_rpm: float, theta=(0.0, 0.0), h: int = 6) -> np.ndarray:
    sp = ph.new_setpoints(udc_v)
    sp[ph.S_POWER] = 1.0
    sp[ph.S_TORQUE_NM] = torque_nm
    sp[ph.S_LOAD_ON] = 1.0
    sp[ph.S_LOAD_SPEED] = speed_rpm * 2.0 * math.pi / 60.0
    sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN] = theta
    sp[ph.S_H] = h
    return sp


def whole_periods(speed_rpm: float, n_p: float, sample_rate_hz: float, periods: int) -> int:
    """Samples spanning `periods` electrical periods (rounded; exact at 2000 rpm / 16 kHz: 120 each)."""
    f_e = speed_rpm / 60.0 * n_p
    return int(round(periods * sample_rate_hz / f_e))


def simulate_op(
    p: np.ndarray,
    tab: np.ndarray,
    sp: np.ndarray,
    torque_nm: float,
    speed_rpm: float,
    udc_v: float,
    settle_s: float = 0.5,
    periods: int = 200,
    noise_seed: int | None = 0,
):
    """Steady state of an OP: returns the trace of `periods` whole electrical periods after settling."""
    plant = ph.Plant(p, tab, noise_seed)
    plant.init_op(torque_nm, speed_rpm, udc_v)
    fs_hz = 1.0 / p[ph.P_TS]
    plant.run(sp, int(settle_s * fs_hz), frames=False)
    n = whole_periods(speed_rpm, p[ph.P_NP], fs_hz, periods)
    return plant.run(sp, n, trace=True, frames=False)[3]


def map_from_op1(sc: scn.Scenario, amp_op1: float, phase_op1_deg: float) -> tuple[list, list]:
    dist = sc.section("disturbance")
    t = np.asarray(dist["torque_nm"], dtype=float)
    n = np.asarray(dist["speed_rpm"], dtype=float)
    tt, nn = np.meshgrid(t, n)
    amp = amp_op1 * (0.3 + 0.7 * (tt / OP1_TORQUE_NM) ** 2) * (0.9 + 0.1 * nn / OP1_SPEED_RPM)
    phase = phase_op1_deg + 12.0 * (tt - OP1_TORQUE_NM) / OP1_TORQUE_NM - 8.0 * (nn - OP1_SPEED_RPM) / 1000.0
    return amp.round(7).tolist(), phase.round(4).tolist()


def calibrate(iterations: int = 4, verbose: bool = True) -> dict:
    sc = scn.load("paper-bench")
    h = int(sc.section("disturbance").get("order", 6))
    theta = theta_from_gamma_delta(math.radians(GAMMA_DEG), math.radians(DELTA_DEG))
    sp = op_setpoints(OP1_UDC_V, OP1_TORQUE_NM, OP1_SPEED_RPM, theta, h)
    dc, ds = 0.0, 0.0  # phasor of d at OP1
    for it in range(iterations + 1):
        amp, phase_deg = math.hypot(dc, ds), math.degrees(math.atan2(-ds, dc))
        sc.data["disturbance"]["amplitude_nm"], sc.data["disturbance"]["phase_deg"] = map_from_op1(sc, amp, phase_deg)
        p, tab = scn.build(sc)
        p[ph.P_NOISE] = 0.0
        tr = simulate_op(p, tab, sp, OP1_TORQUE_NM, OP1_SPEED_RPM, OP1_UDC_V)
        rc, rs = harmonic_phasor(tr[:, ph.TR_TORQUE], tr[:, ph.TR_PHI_E], h)
        if verbose:
            print(f"pass {it}: residual torque harmonic {math.hypot(rc, rs):.3e} Nm")
        if it == iterations:
            break
        dc -= rc
        ds -= rs
    # verification on the measured acceleration (noise off): uncompensated vs theta*
    tr0 = simulate_op(
        p,
        tab,
        op_setpoints(OP1_UDC_V, OP1_TORQUE_NM, OP1_SPEED_RPM, (0.0, 0.0), h),
        OP1_TORQUE_NM,
        OP1_SPEED_RPM,
        OP1_UDC_V,
    )
    tr1 = simulate_op(p, tab, sp, OP1_TORQUE_NM, OP1_SPEED_RPM, OP1_UDC_V)
    a0 = math.hypot(*harmonic_phasor(tr0[:, ph.TR_ALPHA_MEAS], tr0[:, ph.TR_PHI_E], h))
    a1 = math.hypot(*harmonic_phasor(tr1[:, ph.TR_ALPHA_MEAS], tr1[:, ph.TR_PHI_E], h))
    result = {
        "d_op1_nm": amp,
        "phase_op1_deg": phase_deg,
        "theta_cos": theta[0],
        "theta_sin": theta[1],
        "alpha_h_uncompensated_rad_s2": a0,
        "alpha_h_compensated_rad_s2": a1,
        "suppression_db": 20.0 * math.log10(a0 / max(a1, 1e-300)),
        "amplitude_nm": sc.data["disturbance"]["amplitude_nm"],
        "phase_deg": sc.data["disturbance"]["phase_deg"],
    }
    if verbose:
        for k, v in result.items():
            if not isinstance(v, list):
                print(f"{k} = {v:.6g}")
    return result


def write_toml(result: dict, path=None) -> None:
    path = path or scn.resolve("paper-bench")
    text = open(path).read()
    for key in ("amplitude_nm", "phase_deg"):
        rows = ", ".join("[" + ", ".join(f"{v:.7g}" for v in row) + "]" for row in result[key])
        text = re.sub(rf"^{key}\s*=.*$", lambda m: f"{key} = [{rows}]", text, count=1, flags=re.M)
    open(path, "w").write(text)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="write the map into paper-bench.toml")
    args = ap.parse_args(argv)
    result = calibrate()
    if args.write:
        write_toml(result)
        print("written to", scn.resolve("paper-bench"))


if __name__ == "__main__":
    main()
