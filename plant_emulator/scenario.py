"""Scenario files: the emulated bench's truth (TOML), the seeded perturbation, the parameter vector.

A scenario is loaded by name (plant_emulator/scenarios/<name>.toml) or by path. Every field is
documented in docs/scenarios.md (units, ranges, how to write one from a datasheet). `--seed N`
perturbs the truth (never the [firmware] nominal values) uniformly within the ranges of the [seed]
section: R_s, L_d, L_q, psi_p by +-`r_s_rel`, `inductance_rel`, `psi_p_rel`; the sensor resonance
(poles) by +-`resonance_rel`; the disturbance map by a common amplitude factor
+-`disturbance_amplitude_rel` and phase offset +-`disturbance_phase_rad`, plus per cell
+-`disturbance_cell_rel` / +-`disturbance_cell_phase_rad`; each further harmonic ([[disturbance.harmonics]]) by
its own draws within the same ranges.
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
    """Randomise the truth within the [seed] ranges (deterministic for a given seed). Never touches
    [firmware] (what the drive believes) nor the saturation table shapes (only their base values)."""
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
    # disturbance map: one common amplitude factor and phase offset, plus a smaller one per cell
    f_amp = rel("disturbance_amplitude_rel", 0.2)
    span_phase = float(ranges.get("disturbance_phase_rad", 0.35))
    d_phase = rng.uniform(-span_phase, span_phase)
    cell_rel = float(ranges.get("disturbance_cell_rel", 0.1))
    cell_phase = float(ranges.get("disturbance_cell_phase_rad", 0.1))
    amp = np.asarray(dist["amplitude_nm"], dtype=float)
    ph_deg = np.asarray(dist["phase_deg"], dtype=float)
    amp = amp * f_amp * (1.0 + rng.uniform(-cell_rel, cell_rel, amp.shape))
    ph_deg = ph_deg + math.degrees(d_phase) + np.degrees(rng.uniform(-cell_phase, cell_phase, ph_deg.shape))
    dist["amplitude_nm"] = amp.tolist()
    dist["phase_deg"] = ph_deg.tolist()
    # each further harmonic its own draws (after the map's: a seed's map of order h stays what it was)
    for extra in dist.get("harmonics", []) or []:
        f_k = rel("disturbance_amplitude_rel", 0.2)
        phase_k = rng.uniform(-span_phase, span_phase)
        amp_k = np.asarray(extra["amplitude_nm"], dtype=float)
        ph_k = np.asarray(extra["phase_deg"], dtype=float)
        extra["amplitude_nm"] = (amp_k * f_k * (1.0 + rng.uniform(-cell_rel, cell_rel, amp_k.shape))).tolist()
        extra["phase_deg"] = (
            ph_k + math.degrees(phase_k) + np.degrees(rng.uniform(-cell_phase, cell_phase, ph_k.shape))
        ).tolist()
    sc.perturbation = {
        **{k: v for k, v in factors.items()},
        "resonance": f_res,
        "disturbance_amplitude": f_amp,
        "disturbance_phase_rad": d_phase,
    }
    sc.data = data


def validate(sc: Scenario) -> None:
    """Refuse scenarios the physics cannot run (ValueError naming the field)."""
    m = sc.section("machine")
    for key in ("pole_pairs", "r_s_ohm", "l_d_h", "l_q_h", "psi_p_wb"):
        if float(m.get(key, 0.0)) <= 0.0:
            raise ValueError(f"[machine] {key} must be > 0")
    sat = sc.section("saturation")
    if sat:
        axis = np.asarray(sat["current_a"], dtype=float)
        if axis.ndim != 1 or len(axis) < 1 or np.any(np.diff(axis) <= 0):
            raise ValueError("[saturation] current_a must be strictly increasing")
        for key in ("l_d_factor", "l_q_factor", "psi_p_factor"):
            col = np.asarray(sat[key], dtype=float)
            if col.shape != axis.shape or np.any(col <= 0):
                raise ValueError(f"[saturation] {key} needs one positive factor per current_a point")
    dist = sc.section("disturbance")
    t_axis = np.asarray(dist.get("torque_nm", [0.0]), dtype=float)
    n_axis = np.asarray(dist.get("speed_rpm", [0.0]), dtype=float)
    for name, axis in (("torque_nm", t_axis), ("speed_rpm", n_axis)):
        if axis.ndim != 1 or np.any(np.diff(axis) <= 0):
            raise ValueError(f"[disturbance] {name} must be strictly increasing")
    for key in ("amplitude_nm", "phase_deg"):
        arr = np.asarray(dist.get(key, [[0.0]]), dtype=float)
        if arr.shape != (len(n_axis), len(t_axis)):
            raise ValueError(f"[disturbance] {key} must have len(speed_rpm) rows of len(torque_nm) values")
    extras = dist.get("harmonics", []) or []
    if len(extras) > ph.MAX_FURTHER_HARMONICS:
        raise ValueError(f"[disturbance] harmonics: at most {ph.MAX_FURTHER_HARMONICS} further orders")
    orders = [int(dist.get("order", 6))]
    for i, extra in enumerate(extras):
        where = f"[[disturbance.harmonics]] entry {i + 1}"
        order = extra.get("order")
        if not isinstance(order, int) or not 1 <= order <= 48 or order in orders:
            raise ValueError(f"{where}: order must be an integer 1..48 not given before, got {order!r}")
        orders.append(order)
        for key in ("amplitude_nm", "phase_deg"):
            arr = np.asarray(extra.get(key, [[0.0]]), dtype=float)
            if arr.shape != (len(n_axis), len(t_axis)):
                raise ValueError(f"{where}: {key} must have len(speed_rpm) rows of len(torque_nm) values")


def tables(sc: Scenario) -> tuple[np.ndarray, dict]:
    """The flat table array of physics.simulate and the offsets/lengths to put into the parameters."""
    parts: list[np.ndarray] = []
    meta: dict[str, tuple[int, ...]] = {}  # table name -> (its lengths..., offset)
    off = 0
    sat = sc.section("saturation")
    if sat:
        axis = np.asarray(sat["current_a"], dtype=float)
        block = np.concatenate(
            [
                axis,
                np.asarray(sat["l_d_factor"], float),
                np.asarray(sat["l_q_factor"], float),
                np.asarray(sat["psi_p_factor"], float),
            ]
        )
        meta["sat"] = (len(axis), off)
        parts.append(block)
        off += len(block)
    else:
        meta["sat"] = (0, 0)
    dist = sc.section("disturbance")
    t_axis = np.asarray(dist.get("torque_nm", [0.0]), dtype=float)
    n_axis = np.asarray(dist.get("speed_rpm", [0.0]), dtype=float) * 2.0 * math.pi / 60.0
    amp = np.asarray(dist.get("amplitude_nm", [[0.0]]), dtype=float)
    phase = np.radians(np.asarray(dist.get("phase_deg", [[0.0]]), dtype=float))
    block = np.concatenate([t_axis, n_axis, (amp * np.cos(phase)).ravel(), (amp * np.sin(phase)).ravel()])
    meta["dmap"] = (len(t_axis), len(n_axis), off)
    parts.append(block)
    off += len(block)
    # further harmonics (physics.machine.map_phasor): their orders, then X_k, Y_k on the map's axes
    extras = dist.get("harmonics", []) or []
    orders = np.zeros(ph.MAX_FURTHER_HARMONICS)
    phasors = []
    for k, extra in enumerate(extras):
        orders[k] = float(extra["order"])
        amp_k = np.asarray(extra["amplitude_nm"], dtype=float)
        phase_k = np.radians(np.asarray(extra["phase_deg"], dtype=float))
        phasors += [(amp_k * np.cos(phase_k)).ravel(), (amp_k * np.sin(phase_k)).ravel()]
    parts.append(np.concatenate([orders, *phasors]))
    meta["further"] = (len(extras), off)
    tab = np.concatenate(parts) if parts else np.zeros(1)
    return tab, meta


def build(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """(parameter vector, table array) of physics.simulate from a scenario (PI gains by pole-zero
    cancellation: K_p = 2 pi f_bw L_nom, K_i = 2 pi f_bw R_nom, so the closed current loop is a
    first-order lag with bandwidth f_bw apart from the delay)."""
    validate(sc)
    m = sc.section("machine")
    fw = sc.section("firmware")
    dist = sc.section("disturbance")
    mech = sc.section("mechanics")
    sensor = sc.section("sensor")
    load_ = sc.section("load")
    inv = sc.section("inverter")
    sat = sc.section("saturation")
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
    p[ph.P_W_BW] = w_bw
    p[ph.P_KP_D] = w_bw * p[ph.P_LD_NOM]
    p[ph.P_KP_Q] = w_bw * p[ph.P_LQ_NOM]
    p[ph.P_KI_D] = w_bw * p[ph.P_R_NOM]
    p[ph.P_KI_Q] = w_bw * p[ph.P_R_NOM]
    p[ph.P_IMAX] = float(fw["i_max_a"])
    p[ph.P_V_MARGIN] = float(fw.get("voltage_margin", 0.95))
    p[ph.P_FW_BW] = 2.0 * math.pi * float(fw.get("fw_loop_bandwidth_hz", 10.0))
    p[ph.P_FW_TARGET] = float(fw.get("fw_loop_target", 0.98))
    p[ph.P_ANGLE_COMP] = 1.0 if bool(fw.get("angle_compensation", True)) else 0.0
    j = float(mech["inertia_kgm2"])
    p[ph.P_J] = j
    p[ph.P_B] = float(mech.get("viscous_nm_s_per_rad", 0.0))
    b0, b1, b2, a1, a2 = ph.sensor_biquad(
        float(sensor["zero_rad_s"]), float(sensor["pole_re_rad_s"]), float(sensor["pole_im_rad_s"]), ts
    )
    p[ph.P_H_B0], p[ph.P_H_B1], p[ph.P_H_B2], p[ph.P_H_A1], p[ph.P_H_A2] = b0, b1, b2, a1, a2
    fs = float(sensor["full_scale_rad_s2"])
    p[ph.P_ALPHA_FS] = fs
    p[ph.P_NOISE] = float(sensor.get("noise_rms_fraction", 0.0)) * fs
    p[ph.P_DIST_SCALE] = float(dist.get("scale", 1.0))
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
    p[ph.P_T_DEAD] = float(inv.get("dead_time_s", 0.0))
    p[ph.P_F_PWM] = float(inv.get("pwm_frequency_hz", sc.sample_rate_hz))
    p[ph.P_I_ZC] = float(inv.get("zero_current_band_a", 0.5))
    p[ph.P_SAT_DECAY] = math.exp(-ts / float(sat.get("filter_time_s", 1e-3))) if sat else 0.0
    tab, meta = tables(sc)
    p[ph.P_SAT_N], p[ph.P_SAT_OFF] = meta["sat"]
    p[ph.P_DMAP_NT], p[ph.P_DMAP_NN], p[ph.P_DMAP_OFF] = meta["dmap"]
    p[ph.P_XH_N], p[ph.P_XH_OFF] = meta["further"]
    return p, tab


def build_params(sc: Scenario) -> np.ndarray:
    """Parameter vector alone (tables via `build`)."""
    return build(sc)[0]
