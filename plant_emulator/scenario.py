"""Scenario files: the emulated bench's truth (TOML), the seeded perturbation, the parameter vector.

A scenario is loaded by name (plant_emulator/scenarios/<name>.toml) or by path. Every field is
documented with its unit in the TOML itself (see scenarios/paper-bench.toml). `--seed N` perturbs
the truth (never the [firmware] nominal values) uniformly within the ranges of the [seed] section:
R_s, L_d, L_q, psi_p by +-`r_s_rel`, `inductance_rel`, `psi_p_rel`; the sensor resonance (poles)
by +-`resonance_rel`; the disturbance amplitudes by +-`disturbance_amplitude_rel` and its phases
by +-`disturbance_phase_rad`.
"""
from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import physics as ph

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
DEFAULT_SCENARIO = "paper-bench"


@dataclass
class Scenario:
    name: str
    data: dict
    seed: int | None = None
    source: str = ""
    perturbation: dict = field(default_factory=dict)

    # convenient accessors
    def section(self, name: str) -> dict:
        return self.data.get(name, {})

    @property
    def sample_rate_hz(self) -> float:
        return float(self.section("bench").get("sample_rate_hz", 16000))

    @property
    def udc_v(self) -> float:
        return float(self.section("bench").get("udc_v", 12.0))

    @property
    def rated_torque_nm(self) -> float:
        return float(self.section("firmware").get("rated_torque_nm", 5.0))


def resolve(name_or_path: str | None) -> Path:
    """Scenario file for a name ('paper-bench') or a path."""
    if not name_or_path:
        name_or_path = DEFAULT_SCENARIO
    path = Path(name_or_path)
    if path.is_file():
        return path
    candidate = SCENARIO_DIR / f"{name_or_path}.toml"
    if candidate.exists():
        return candidate
    raise FileNotFoundError(f"no scenario {name_or_path!r} (not a file, not in {SCENARIO_DIR})")


def load(name_or_path: str | None = None, seed: int | None = None) -> Scenario:
    path = resolve(name_or_path)
    with open(path, "rb") as fh:
        data = tomllib.load(fh)
    sc = Scenario(name=str(data.get("name", path.stem)), data=data, seed=seed, source=str(path))
    if seed is not None:
        perturb(sc, seed)
    return sc


def perturb(sc: Scenario, seed: int) -> None:
    """Randomise the truth within the [seed] ranges (deterministic for a given seed)."""
    rng = np.random.default_rng(seed)
    ranges = sc.section("seed")
    data = copy.deepcopy(sc.data)
    m, dist, sensor = data["machine"], data["disturbance"], data["sensor"]

    def rel(key: str, default: float) -> float:
        span = float(ranges.get(key, default))
        return 1.0 + rng.uniform(-span, span)

    factors = {
        "r_s_ohm": rel("r_s_rel", 0.2),
        "l_d_h": rel("inductance_rel", 0.2),
        "l_q_h": rel("inductance_rel", 0.2),
        "psi_p_wb": rel("psi_p_rel", 0.2),
    }
    for key, f in factors.items():
        m[key] = float(m[key]) * f
    f_res = rel("resonance_rel", 0.1)
    sensor["pole_re_rad_s"] = float(sensor["pole_re_rad_s"]) * f_res
    sensor["pole_im_rad_s"] = float(sensor["pole_im_rad_s"]) * f_res
    f_amp = rel("disturbance_amplitude_rel", 0.2)
    dist["d0_nm"] = float(dist["d0_nm"]) * f_amp
    dist["d2_nm"] = float(dist["d2_nm"]) * f_amp
    span_phase = float(ranges.get("disturbance_phase_rad", 0.35))
    dist["phase_rad"] = float(dist["phase_rad"]) + rng.uniform(-span_phase, span_phase)
    dist["phase_2h_rad"] = float(dist.get("phase_2h_rad", 0.0)) + rng.uniform(-span_phase, span_phase)
    sc.perturbation = {**{k: v for k, v in factors.items()}, "resonance": f_res, "disturbance_amplitude": f_amp}
    sc.data = data


def build_params(sc: Scenario) -> np.ndarray:
    """Parameter vector of physics.simulate_chunk from a scenario (PI gains by pole-zero
    cancellation: K_p = 2 pi f_bw L_nom, K_i = 2 pi f_bw R_nom, so the closed current loop is a
    first-order lag with bandwidth f_bw apart from the delay)."""
    m = sc.section("machine")
    fw = sc.section("firmware")
    dist = sc.section("disturbance")
    mech = sc.section("mechanics")
    sensor = sc.section("sensor")
    load_ = sc.section("load")
    p = np.zeros(ph.N_PARAMS)
    ts = 1.0 / sc.sample_rate_hz
    p[ph.P_TS] = ts
    p[ph.P_NP] = float(m["pole_pairs"])
    p[ph.P_R] = float(m["r_s_ohm"])
    p[ph.P_LD] = float(m["l_d_h"])
    p[ph.P_LQ] = float(m["l_q_h"])
    p[ph.P_PSI] = float(m["psi_p_wb"])
    p[ph.P_R_NOM] = float(fw["r_s_ohm"])
    p[ph.P_LD_NOM] = float(fw["l_d_h"])
    p[ph.P_LQ_NOM] = float(fw["l_q_h"])
    p[ph.P_PSI_NOM] = float(fw["psi_p_wb"])
    w_bw = 2.0 * math.pi * float(fw["current_bandwidth_hz"])
    p[ph.P_KP_D] = w_bw * p[ph.P_LD_NOM]
    p[ph.P_KP_Q] = w_bw * p[ph.P_LQ_NOM]
    p[ph.P_KI_D] = w_bw * p[ph.P_R_NOM]
    p[ph.P_KI_Q] = w_bw * p[ph.P_R_NOM]
    p[ph.P_IMAX] = float(fw["i_max_a"])
    j = float(mech["inertia_kgm2"])
    p[ph.P_J] = j
    p[ph.P_B] = float(mech.get("viscous_nm_s_per_rad", 0.0))
    b0, b1, b2, a1, a2 = ph.sensor_biquad(float(sensor["zero_rad_s"]), float(sensor["pole_re_rad_s"]),
                                          float(sensor["pole_im_rad_s"]), ts)
    p[ph.P_H_B0], p[ph.P_H_B1], p[ph.P_H_B2], p[ph.P_H_A1], p[ph.P_H_A2] = b0, b1, b2, a1, a2
    fs = float(sensor["full_scale_rad_s2"])
    p[ph.P_ALPHA_FS] = fs
    p[ph.P_NOISE] = float(sensor.get("noise_rms_fraction", 0.0)) * fs
    p[ph.P_D0] = float(dist.get("d0_nm", 0.0))
    p[ph.P_D2] = float(dist.get("d2_nm", 0.0))
    p[ph.P_PHI_D] = float(dist.get("phase_rad", 0.0))
    p[ph.P_D2_RATIO] = float(dist.get("ratio_2h", 0.0))
    p[ph.P_PHI_D2] = float(dist.get("phase_2h_rad", 0.0))
    p[ph.P_T_RATED] = sc.rated_torque_nm
    p[ph.P_H_DIST] = float(dist.get("order", 6))
    # load speed loop: P part sets the crossover w_c = K_p/J, PI corner a quarter below it
    w_c = 2.0 * math.pi * float(load_.get("speed_bandwidth_hz", 8.0))
    p[ph.P_LOAD_KP] = j * w_c
    p[ph.P_LOAD_KI] = j * w_c * w_c / 4.0
    p[ph.P_LOAD_RAMP] = float(load_.get("ramp_rpm_per_s", 20000.0)) * 2.0 * math.pi / 60.0
    p[ph.P_LOAD_TMAX] = float(load_.get("max_torque_nm", 20.0))
    tau_off = float(fw.get("current_decay_off_s", 2e-4))
    p[ph.P_OFF_DECAY] = math.exp(-ts / tau_off)
    return p
