"""Probe identification (ours: docs/conventions.md, Beyond the paper (a)).

The steady state is affine in theta (eq. 15): a = S_ss (theta_d + theta). Two probe injections
p1 = [P, 0], p2 = [0, P] around the current theta measure the 2x2 real matrix S_ss column by
column (no assumption that it has the rotation structure of a scalar complex gain):

    S_ss[:, k] = (a(theta + p_k) - a(theta)) / P

and one Newton step lands on theta* = theta - S_ss^-1 a(theta) = -theta_d. The plant is only nearly
affine (inverter dead time and saturation bend it), so each further step also refines S_ss from what
that step measured (Broyden's update S <- S + (da - S dtheta) dtheta^T / |dtheta|^2, exact for an
affine plant; skipped when the step moved the phasor by less than 20 noise levels).

When it stops: as soon as a window shows the residual below the target with confidence
(common.meets), or when a step no longer improves it (noise floor or non-linearity), or after
`max_newton_steps`. Each window is as long as its purpose needs (common module doc): a step's window
resolves the residual it expects to one twentieth, the last ones resolve the target to one fifth.

A sweep's neighbours (common.Prior) give a starting theta and a measured S_ss: then no probe is
needed, the first Newton step starts from theta_prior. Where the sensor is over range at theta = 0
(a harmonic next to the shaft resonance), the run starts from the prior theta and the uncompensated
phasor is computed from the affine model, A_0 = a(theta) - S_ss theta, and reported as estimated.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
from pydantic import Field

from service.identification.common import (
    PRECISION_FOR_TARGET,
    Conditions,
    MethodOptions,
    Prior,
    clamp,
    done,
    measure_reference,
    measure_step,
    noise_floor_db,
    periods_for,
    spectrum_traces,
    stop_amplitude,
    target_amplitude,
    time_to_suppression,
    verdict,
)
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementError, MeasurementSession, Window
from service.model.harmonic import Phasor
from service.model.secondary_path import phase_error_deg, rotation_part, s_matrix

HISTORY_COLUMNS = ["plant_time_s", "theta_cos", "theta_sin", "amplitude_fs"]


class ProbeOptions(MethodOptions):
    probe_fraction: float = Field(0.5, gt=0, le=1.0, description="probe size as a fraction of the model's |theta*|")
    probe_min_deg: float = Field(0.3, gt=0, le=10, description="smallest probe amplitude, deg")
    probe_max_deg: float = Field(4.0, gt=0, le=20, description="largest probe amplitude, deg (kept <= gamma_max/2)")
    window_s: float = Field(
        0.01, gt=0, le=1.0, description="shortest window, plant s (whole electrical turns, >= 12 periods)"
    )
    max_newton_steps: int = Field(6, ge=1, le=50)
    use_prior: bool = Field(True, description="start from the neighbours' theta and S when a sweep provides them")

    def plant_time_bound_s(self, harmonic_frequency_hz: float) -> float:
        """Worst-case plant time (s): reference (2 windows), prior start, 2 probes, the Newton steps,
        a second pair of probes, the confirmation; every window at most max_window_s after settle_s."""
        return (2 * self.max_newton_steps + 8) * (self.max_window_s + self.settle_s)


def _row(w: Window, theta: np.ndarray) -> list[float]:
    return [w.end_time_s, float(theta[0]), float(theta[1]), w.phasor.amplitude]


PROBE_MAX_RESPONSE_FS = 0.2  # a probe moves alpha by at most this (model): it stays in the sensor's range


def _probe_size(amplitude_fs: float, s_hat: complex, gamma_max_rad: float, options: ProbeOptions) -> float:
    """Probe amplitude (rad): a fraction of the model's |theta*|, within the options' bounds, half of
    gamma_max, and small enough that the model's response stays well inside the sensor's range."""
    model_theta_rad = amplitude_fs / abs(s_hat)
    return min(
        max(options.probe_fraction * model_theta_rad, math.radians(options.probe_min_deg)),
        math.radians(options.probe_max_deg),
        gamma_max_rad / 2,
        PROBE_MAX_RESPONSE_FS / abs(s_hat),
    )


PROBE_HALVINGS = 3  # a probe that drives the sensor over range is halved, at most this often


def _probe_within_range(
    session: MeasurementSession,
    theta: np.ndarray,
    a: np.ndarray,
    probe_rad: float,
    s_hat: complex,
    min_periods: int,
    max_periods: int,
    history: list[list[float]],
    notes: list[str],
) -> tuple[np.ndarray, float]:
    """S_ss from two probes; where the model underestimated the path (a shaft resonance nearer than
    the settings say) and a probe drives the sensor over range, the probe is halved and measured again."""
    for halvings in range(PROBE_HALVINGS + 1):
        try:
            s_ss = measure_s_matrix(
                session, theta, a, probe_rad, min_periods, max_periods, abs(s_hat) * probe_rad / 50, history
            )
        except MeasurementError as exc:
            if not exc.over_range or halvings == PROBE_HALVINGS:
                raise
            probe_rad /= 2
            continue
        if halvings:
            notes.append(
                f"probes halved {halvings} time(s) to {math.degrees(probe_rad):.2f} deg: the sensor went over range"
            )
        return s_ss, probe_rad
    raise AssertionError("unreachable")


def measure_s_matrix(
    session: MeasurementSession,
    theta: np.ndarray,
    a_at_theta: np.ndarray,
    probe_rad: float,
    periods: int,
    max_periods: int,
    noise_limit_fs: float,
    history: list[list[float]],
) -> np.ndarray:
    """S_ss measured by two probes around theta (one column each)."""
    columns = []
    for k in range(2):
        p = np.zeros(2)
        p[k] = probe_rad
        session.apply_theta(*(theta + p))
        w = session.measure(periods, max_noise_std_fs=noise_limit_fs, max_periods=max_periods)
        history.append(_row(w, theta + p))
        columns.append((w.phasor.vector - a_at_theta) / probe_rad)
    return np.column_stack(columns)


def identify_probe(
    session: MeasurementSession,
    s_hat: complex,
    options: ProbeOptions,
    gamma_max_rad: float,
    *,
    prior: Prior | None = None,
    conditions: Conditions | None = None,
    before: Window | None = None,
    start_theta: tuple[float, float] | None = None,
    history: list[list[float]] | None = None,
    method: str = "probe",
    details: dict[str, Any] | None = None,
) -> IdentificationResult:
    """Probe + Newton. The adaptive method's fallback passes what it has already measured (the
    uncompensated window, its history) and the best theta it saw, to start from there."""
    h = session.harmonic_order
    session.settle_after_theta_s = options.settle_s
    min_periods = periods_for(session, options.window_s)
    max_periods = max(min_periods, periods_for(session, options.max_window_s))
    prior = prior if options.use_prior else None
    notes: list[str] = []
    if before is None:
        try:
            before = measure_reference(session, min_periods, max_periods)
        except MeasurementError as exc:
            if not exc.over_range:
                raise
            if prior is None:
                raise MeasurementError(
                    "sensor over range without compensation and no neighbouring result to start "
                    "from: measure this point in a sweep with its neighbours, or at lower torque",
                    over_range=True,
                ) from None
            notes.append(
                "sensor over range at theta = 0: started from the neighbours' theta, uncompensated "
                "phasor estimated from the affine model"
            )
    history = (
        history
        if history is not None
        else ([[before.end_time_s, 0.0, 0.0, before.phasor.amplitude]] if before is not None else [])
    )
    theta = np.zeros(2)
    a = before.phasor.vector if before is not None else None
    s_model = s_matrix(s_hat)
    start = np.array(start_theta, dtype=float) if start_theta is not None and any(start_theta) else None
    if start is None and prior is not None and np.any(prior.theta):
        start = prior.theta
    w: Window | None  # a Newton step's window is None when it failed
    if start is not None:
        theta, _ = clamp(start, gamma_max_rad)
        session.apply_theta(*theta)
        expected = abs(before.phasor.complex) if before is not None else None
        w = session.measure(
            min_periods, max_noise_std_fs=None if expected is None else expected / 50, max_periods=max_periods
        )
        a = w.phasor.vector
        history.append(_row(w, theta))
    # None only over range at theta = 0 with a zero prior theta: that edge fails below as it always has
    a = cast(np.ndarray, a)
    s_ss = prior.s() if prior is not None and prior.s_matrix is not None else None
    probe_rad = 0.0
    if s_ss is None:
        probe_rad = _probe_size(float(np.hypot(*a)), s_hat, gamma_max_rad, options)
        theta, _ = clamp(theta, gamma_max_rad - probe_rad)  # the probes go around theta: stay inside gamma_max
        s_ss, probe_rad = _probe_within_range(
            session, theta, a, probe_rad, s_hat, min_periods, max_periods, history, notes
        )
        s_probed = s_ss.copy()
    else:
        s_probed = None
        assert prior is not None  # s_ss came from it
        notes.append(f"started from {prior.source or 'a prior'} (theta and measured S)")
    if abs(np.linalg.det(s_ss)) < 1e-30:
        raise MeasurementError("the probe response is zero: the injection has no effect on the measured harmonic here")

    uncompensated = before.phasor.amplitude if before is not None else float(np.hypot(*(a - s_ss @ theta)))
    limit = target_amplitude(uncompensated, options.target_db)
    stop_at = stop_amplitude(uncompensated, options)
    best_theta, best_amp, best_a = theta.copy(), float(np.hypot(*a)), a
    failures = 0
    final: Window | None = None
    limited = False
    damping = 1.0
    steps = 0
    for steps in range(1, options.max_newton_steps + 1):
        target = theta - damping * np.linalg.solve(s_ss, a)
        new_theta, limited = clamp(target, gamma_max_rad)
        session.apply_theta(*new_theta)
        # a Newton step is expected to leave a tenth of now; None: it overshot into the resonance, a
        # failed step, half as long next time
        w = measure_step(session, min_periods, max_periods, limit, max(0.1 * float(np.hypot(*a)), limit))
        if w is not None:
            history.append(_row(w, new_theta))
            new_a = w.phasor.vector
            d_theta, d_a = new_theta - theta, new_a - a
            if float(np.hypot(*(s_ss @ d_theta))) > 20.0 * max(w.noise_std_fs, 1e-12) * math.sqrt(2):
                broyden = s_ss + np.outer(d_a - s_ss @ d_theta, d_theta) / float(d_theta @ d_theta)
                if abs(np.linalg.det(broyden)) > 1e-30:
                    s_ss = broyden
            if done(w, limit, stop_at):
                final = w
                best_theta = new_theta.copy()
                break
        improved = w is not None and w.phasor.amplitude < 0.8 * best_amp
        if w is not None and w.phasor.amplitude < best_amp:
            best_theta, best_amp, best_a = new_theta.copy(), w.phasor.amplitude, new_a
        failures = 0 if improved else failures + 1
        damping = 1.0 if improved else 0.5 * damping
        if failures >= 2:
            if s_probed is not None:
                break  # the residual stopped improving: noise floor (or non-linearity) reached
            # the neighbours' S does not hold here: measure it with the probes, around the best point
            probe_rad = _probe_size(float(np.hypot(*best_a)), s_hat, gamma_max_rad, options)
            theta, _ = clamp(best_theta, gamma_max_rad - probe_rad)
            if not np.allclose(theta, best_theta):
                session.apply_theta(*theta)
                w = session.measure(
                    min_periods,
                    max_noise_std_fs=max(limit / PRECISION_FOR_TARGET, best_amp / 50),
                    max_periods=max_periods,
                )
                history.append(_row(w, theta))
                best_a = w.phasor.vector
            s_ss, probe_rad = _probe_within_range(
                session, theta, best_a, probe_rad, s_hat, min_periods, max_periods, history, notes
            )
            s_probed = s_ss.copy()
            notes.append("the neighbours' S did not hold here: measured by probes")
            failures, damping, a = 0, 1.0, best_a
            continue
        # the next step starts from the best point, with the S that this step refined
        theta, a = (new_theta, new_a) if improved else (best_theta.copy(), best_a)
    if final is None:
        # confirm the best theta with the precision the target needs (or the longest window allowed)
        session.apply_theta(*best_theta)
        final = session.measure(min_periods, max_noise_std_fs=limit / PRECISION_FOR_TARGET, max_periods=max_periods)
        history.append(_row(final, best_theta))
    if before is None:
        uncompensated = float(np.hypot(*(a - s_ss @ theta)))  # the affine model with the refined S_ss
        limit = target_amplitude(uncompensated, options.target_db)
    suppression = 20.0 * math.log10(max(uncompensated, 1e-300) / max(final.phasor.amplitude, 1e-300))
    status, message = verdict(suppression, options.target_db, final, uncompensated, conditions, limited)
    how = f"{steps} Newton step(s)" + (f" after 2 probes of {math.degrees(probe_rad):.2f} deg" if probe_rad else "")
    message = f"{message} ({how})" + "".join(f"; {n}" for n in notes)
    s_reported = s_probed if s_probed is not None else s_ss
    s_measured = rotation_part(s_reported)
    residual = a - s_ss @ theta
    uncompensated_phasor = before.phasor if before is not None else Phasor(float(residual[0]), float(residual[1]), 0, 0)
    return IdentificationResult(
        method=method,
        harmonic_order=h,
        status=status,
        message=message,
        theta_cos=float(best_theta[0]),
        theta_sin=float(best_theta[1]),
        residual=final.phasor,
        uncompensated=uncompensated_phasor,
        plant_time_s=session.plant_time_s,
        windows_used=len(history),
        windows_discarded=session.windows_discarded,
        s_model=s_hat,
        s_measured=s_measured,
        target_db=options.target_db,
        noise_floor_db=noise_floor_db(final, uncompensated),
        details={
            **(details or {}),
            "probe_deg": math.degrees(probe_rad),
            "newton_steps": steps,
            "s_matrix": s_reported.tolist(),
            "s_matrix_refined": s_ss.tolist(),
            "s_model_matrix": s_model.tolist(),
            "model_gain_error_db": 20 * math.log10(abs(s_hat) / abs(s_measured)),
            "model_phase_error_deg": phase_error_deg(s_hat, s_measured),
            "uncompensated_estimated": before is None,
            "prior": None if prior is None else prior.source,
            "time_to_40db_s": time_to_suppression(history, uncompensated, 40.0),
        },
        traces={"theta_history": history, "theta_history_columns": HISTORY_COLUMNS, **spectrum_traces(before, final)},
    )
