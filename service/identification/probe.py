"""Probe identification (ours, DESIGN section 3 "going beyond the paper", (a)).

The steady state is affine in theta (eq. 15): a = S_ss (theta_d + theta). Two probe injections
p1 = [P, 0], p2 = [0, P] around the current theta measure the 2x2 real matrix S_ss column by
column (no assumption that it has the rotation structure of a scalar complex gain):

    S_ss[:, k] = (a(theta + p_k) - a(theta)) / P

and one Newton step lands on theta* = theta - S_ss^-1 a(theta) = -theta_d. The plant is only nearly
affine (inverter dead time and saturation bend it), so each further step also refines S_ss from what
that step measured (Broyden's update S <- S + (da - S dtheta) dtheta^T / |dtheta|^2, exact for an
affine plant; skipped when the step moved the phasor by less than 20 noise levels), until the
residual stops improving. The probe-measured S_ss is what the result reports. The probe size P is chosen from the model so the probe's response stands well
above the noise but the injection stays small (linear) and below gamma_max.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.identification.common import measure_uncompensated, spectrum_traces, time_to_suppression, verify
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementSession, Window
from service.secondary_path import phase_error_deg, rotation_part


class ProbeOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    probe_fraction: float = Field(0.5, gt=0, le=1.0, description="probe size as a fraction of the model's |theta*|")
    probe_min_deg: float = Field(0.3, gt=0, description="smallest probe amplitude, deg")
    probe_max_deg: float = Field(4.0, gt=0, description="largest probe amplitude, deg (kept <= gamma_max/2)")
    window_periods: int = Field(24, ge=2, le=10_000)
    settle_s: float = Field(0.04, ge=0, le=10, description="plant time after each theta before measuring")
    max_newton_steps: int = Field(6, ge=1, le=50)
    verify_periods: int = Field(144, ge=2)
    reference_periods: int = Field(72, ge=2, description="periods of the uncompensated reference measurement")
    gamma_max_deg: float | None = Field(None, gt=0, le=45)


def measure_s_matrix(session: MeasurementSession, theta: np.ndarray, a_at_theta: np.ndarray, probe_rad: float,
                     window_periods: int, history: list) -> np.ndarray:
    """S_ss measured by two probes around theta (one column each)."""
    columns = []
    for k in range(2):
        p = np.zeros(2)
        p[k] = probe_rad
        session.apply_theta(*(theta + p))
        w = session.measure(window_periods)
        history.append([w.end_time_s, *(theta + p), w.phasor.amplitude])
        columns.append((w.phasor.vector - a_at_theta) / probe_rad)
    return np.column_stack(columns)


def clamp(v: np.ndarray, gamma_max_rad: float) -> np.ndarray:
    g = float(np.hypot(*v))
    return v * (gamma_max_rad / g) if g > gamma_max_rad else v


def identify_probe(session: MeasurementSession, s_hat: complex, options: ProbeOptions, gamma_max_rad: float, *,
                   before: Window | None = None, start_theta: tuple[float, float] | None = None,
                   history: list | None = None, method: str = "probe",
                   details: dict | None = None) -> IdentificationResult:
    """Probe + Newton. The adaptive method's fallback passes what it has already measured (the
    uncompensated window, its history) and the best theta it saw, to start the probes from there."""
    h = session.harmonic_order
    session.settle_after_theta_s = options.settle_s
    if before is None:
        before = measure_uncompensated(session, options.reference_periods)
    history = history if history is not None else [[before.end_time_s, 0.0, 0.0, before.phasor.amplitude]]
    theta = np.zeros(2)
    a = before.phasor.vector
    if start_theta is not None and any(start_theta):
        theta = np.array(start_theta, dtype=float)
        session.apply_theta(*theta)
        w = session.measure(options.window_periods)
        a = w.phasor.vector
        history.append([w.end_time_s, *theta, w.phasor.amplitude])
    model_theta_rad = abs(before.phasor.complex / s_hat)
    probe_rad = min(max(options.probe_fraction * model_theta_rad, math.radians(options.probe_min_deg)),
                    math.radians(options.probe_max_deg), gamma_max_rad / 2)
    # the probes go around theta: keep theta + p inside gamma_max
    theta = clamp(theta, gamma_max_rad - probe_rad)
    s_ss = measure_s_matrix(session, theta, a, probe_rad, options.window_periods, history)
    s_probed = s_ss.copy()
    if abs(np.linalg.det(s_ss)) < 1e-30:
        raise ValueError("probe response is zero: the injection has no effect on the measured harmonic here")
    s_inv = np.linalg.inv(s_ss)
    best_theta, best_amp = theta.copy(), float(np.hypot(*a))
    limited = False
    steps = 0
    for steps in range(1, options.max_newton_steps + 1):
        target = theta - s_inv @ a
        new_theta = clamp(target, gamma_max_rad)
        limited = not np.allclose(new_theta, target)
        session.apply_theta(*new_theta)
        w = session.measure(options.window_periods)
        history.append([w.end_time_s, *new_theta, w.phasor.amplitude])
        improved = w.phasor.amplitude < 0.8 * best_amp
        new_a = w.phasor.vector
        d_theta, d_a = new_theta - theta, new_a - a
        # only a step that moves the phasor well above the noise of one window says anything about S
        noise = float(np.std(w.alpha_fs)) * math.sqrt(2.0 / len(w.alpha_fs))
        if float(np.hypot(*(s_ss @ d_theta))) > 20.0 * noise:
            broyden = s_ss + np.outer(d_a - s_ss @ d_theta, d_theta) / float(d_theta @ d_theta)
            if abs(np.linalg.det(broyden)) > 1e-30:
                s_ss, s_inv = broyden, np.linalg.inv(broyden)
        theta, a = new_theta, new_a
        if w.phasor.amplitude < best_amp:
            best_theta, best_amp = theta.copy(), w.phasor.amplitude
        if not improved:
            break       # the residual stopped improving: noise floor (or non-linearity) reached
    after = verify(session, *best_theta, options.verify_periods)
    s_measured = rotation_part(s_probed)
    status, message = "ok", f"{steps} Newton step(s) after 2 probes of {math.degrees(probe_rad):.2f} deg"
    if limited and best_amp > 0.1 * before.phasor.amplitude:
        status = "no_authority"
        message = (f"theta* needs more than gamma_max = {math.degrees(gamma_max_rad):.1f} deg "
                   "(the injection cannot cancel the harmonic here, sec. 2.4)")
    return IdentificationResult(
        method=method, harmonic_order=h, status=status, message=message,
        theta_cos=float(best_theta[0]), theta_sin=float(best_theta[1]), residual=after.phasor,
        uncompensated=before.phasor, plant_time_s=session.plant_time_s, windows_used=len(history) + 1,
        windows_discarded=session.windows_discarded, s_model=s_hat, s_measured=s_measured,
        details={**(details or {}), "probe_deg": math.degrees(probe_rad), "newton_steps": steps,
                 "s_matrix": s_probed.tolist(), "s_matrix_refined": s_ss.tolist(),
                 "model_gain_error_db": 20 * math.log10(abs(s_hat) / abs(s_measured)),
                 "model_phase_error_deg": phase_error_deg(s_hat, s_measured),
                 "time_to_40db_s": time_to_suppression(history, before.phasor.amplitude, 40.0)},
        traces={"theta_history": history, "theta_history_columns": ["plant_time_s", "theta_cos", "theta_sin", "amplitude_fs"],
                **spectrum_traces(before, after)},
    )
