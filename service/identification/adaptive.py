"""Adaptive identification (paper sec. 2.3) in block form (docs/conventions.md, Adaptive law).

Continuous law (eq. 16): d(theta)/dt = -2 mu S_hat^+ x(t) alpha(t). Averaged over whole periods of
the harmonic, x(t) alpha(t) averages to a/2 with a = [a_c, a_s], so over one block of length
T_block the update is

    theta <- theta - mu * T_block * S_hat^+ a

With S_hat = S this is a contraction by (1 - g), g = mu T_block, per block; with a phase error phi it
is |1 - g (|S|/|S_hat|) e^{j phi}|, which is < 1 for small g iff |phi| < 90 deg. Blocks last
`block_s` of plant time (whole electrical turns), so g does not depend on the speed.

S_hat (docs/conventions.md, Beyond the paper (c)): it starts as the model of eq. 14-20 (or as the
S measured at the neighbouring cells of a sweep) and is replaced by the S_ss fitted over the run's own blocks (the affine model
a = S_ss theta + b by least squares, common.affine_s_from_history) once the thetas span both
directions and the two disagree by more than `s_refine_tolerance`; the result reports the model
against the measured S.

Limits (sec. 2.4): |theta| <= gamma_max with the state itself clamped (anti-windup); adaptation is
held off where the model says the injection lacks the authority to cancel the harmonic (the gamma
it needs, |A_0 / S_hat|, is more than 1.5 gamma_max).
Stopping: done when a block shows the residual below the target with confidence (common.meets);
stopped when it no longer falls (noise floor) or after `max_blocks`; diverged when the residual grows
well above the best seen or theta runs into gamma_max without the residual falling -- then the best
theta seen is restored and the probe method takes over from there.
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
    affine_s_from_history,
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
from service.identification.probe import HISTORY_COLUMNS, ProbeOptions, identify_probe
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementError, MeasurementSession, Window
from service.model.secondary_path import phase_error_deg, rotation_part, s_matrix


class AdaptiveOptions(MethodOptions):
    mu_per_s: float = Field(25.0, gt=0, le=1000, description="adaptation gain mu of eq. 16, 1/s")
    block_s: float = Field(0.03, gt=0, le=1.0, description="plant time per adaptation block (whole electrical turns)")
    max_blocks: int = Field(40, ge=1, le=1000)
    stall_blocks: int = Field(6, ge=2, le=1000, description="blocks without a 10 % better residual that end the run")
    max_plant_s: float = Field(5.0, gt=0, le=60, description="plant time after which the run ends with what it has")
    divergence_factor: float = Field(
        2.0, gt=1, le=100, description="residual above this times the best seen counts as growing"
    )
    divergence_blocks: int = Field(3, ge=1, le=100, description="consecutive growing blocks that mean divergence")
    fallback: bool = Field(True, description="on divergence, fall back to the probe method")
    s_refine: bool = Field(
        True,
        description="replace S_hat by the S fitted over the run's own blocks where the two "
        "disagree by more than s_refine_tolerance",
    )
    s_refine_tolerance: float = Field(
        0.15, gt=0, le=10, description="relative |S_fit - S_hat| that triggers the replacement"
    )
    use_prior: bool = Field(True, description="start from the neighbours' theta and S when a sweep provides them")
    s_hat_phase_offset_deg: float = Field(
        0.0, ge=-180, le=180, description="deliberate phase error added to S_hat (robustness tests)"
    )

    def plant_time_bound_s(self, harmonic_frequency_hz: float) -> float:
        """Worst-case plant time (s): the blocks stop once max_plant_s is passed (one block late at
        most), plus reference, confirmation and the probe fallback with its defaults."""
        window_s = self.max_window_s + self.settle_s
        probe = ProbeOptions(max_window_s=self.max_window_s, settle_s=self.settle_s)
        return self.max_plant_s + 4 * window_s + probe.plant_time_bound_s(harmonic_frequency_hz)


def _row(w: Window, theta: np.ndarray) -> list[float]:
    return [w.end_time_s, float(theta[0]), float(theta[1]), w.phasor.amplitude]


def identify_adaptive(
    session: MeasurementSession,
    s_hat: complex,
    options: AdaptiveOptions,
    gamma_max_rad: float,
    *,
    prior: Prior | None = None,
    conditions: Conditions | None = None,
) -> IdentificationResult:
    session.settle_after_theta_s = options.settle_s
    prior = prior if options.use_prior else None
    block_periods = periods_for(session, options.block_s)
    max_periods = max(block_periods, periods_for(session, options.max_window_s))
    gain = min(options.mu_per_s * block_periods / session.harmonic_frequency_hz, 1.0)  # g = mu T_block
    offset = complex(
        math.cos(math.radians(options.s_hat_phase_offset_deg)), math.sin(math.radians(options.s_hat_phase_offset_deg))
    )
    s_model = s_matrix(s_hat * offset)
    s_prior = prior.s() if prior is not None and prior.s_matrix is not None else None
    s_used = s_prior if s_prior is not None else s_model
    s_source = prior.source if prior is not None and s_used is not s_model else "model (eq. 14-20)"
    try:
        before = measure_reference(session, block_periods, max_periods)
    except MeasurementError as exc:
        if not exc.over_range or prior is None:
            raise
        # next to the resonance: the probe method starts from the neighbours and estimates A_0 (its doc)
        result = identify_probe(
            session,
            s_hat,
            ProbeOptions(target_db=options.target_db, max_window_s=options.max_window_s),
            gamma_max_rad,
            prior=prior,
            conditions=conditions,
            method="adaptive",
            details={"fallback": "probe", "fallback_reason": "sensor over range at theta = 0"},
        )
        result.message = f"sensor over range at theta = 0, probe from the neighbours: {result.message}"
        return result
    history = [_row(before, np.zeros(2))]
    uncompensated = before.phasor.amplitude
    limit = target_amplitude(uncompensated, options.target_db)
    stop_at = stop_amplitude(uncompensated, options)

    needed_gamma = abs(before.phasor.complex / s_hat)
    if needed_gamma > 1.5 * gamma_max_rad:
        # sec. 2.4: hold the adaptation off; nothing above 0 is sent
        message = (
            f"model needs gamma = {math.degrees(needed_gamma):.1f} deg > gamma_max = "
            f"{math.degrees(gamma_max_rad):.1f} deg: adaptation held off (sec. 2.4)"
        )
        return _result(
            session,
            "no_authority",
            message,
            np.zeros(2),
            before,
            before,
            history,
            s_hat,
            None,
            options,
            {"blocks": 0, "needed_gamma_deg": math.degrees(needed_gamma)},
        )

    theta, window = np.zeros(2), before
    thetas, phasors = [theta.copy()], [before.phasor.vector]
    if prior is not None and np.any(prior.theta):
        theta, _ = clamp(prior.theta, gamma_max_rad)
        session.apply_theta(*theta)
        window = session.measure(
            block_periods,
            max_noise_std_fs=max(limit / PRECISION_FOR_TARGET, uncompensated / 200),
            max_periods=max_periods,
        )
        history.append(_row(window, theta))
        thetas.append(theta.copy())
        phasors.append(window.phasor.vector)
    best_theta, best_amp = theta.copy(), window.phasor.amplitude
    growing = at_limit = 0
    limited = diverged = over_range = False
    final: Window | None = window if done(window, limit, stop_at) and len(history) > 1 else None
    s_replaced_after = None
    blocks = best_block = 0
    for blocks in range(1, options.max_blocks + 1):
        if final is not None:
            break
        a = window.phasor.vector
        step = gain * (np.linalg.pinv(s_used) @ a)  # eq. 16, block form
        theta, limited = clamp(theta - step, gamma_max_rad)
        session.apply_theta(*theta)
        expected = max((1.0 - 0.7 * gain) * window.phasor.amplitude, limit)
        stepped = measure_step(session, block_periods, max_periods, limit, expected)
        if stepped is None:
            # the step drove the sensor over range: S_hat is far off here (a resonance nearer than the
            # settings say); handled as a divergence: best theta back, probe from there
            diverged, over_range = True, True
            break
        window = stepped
        amp = window.phasor.amplitude
        history.append(_row(window, theta))
        thetas.append(theta.copy())
        phasors.append(window.phasor.vector)
        if amp < 0.9 * best_amp:
            best_block = blocks
        if amp < best_amp:
            best_theta, best_amp = theta.copy(), amp
        if done(window, limit, stop_at):
            final = window
            break
        if options.s_refine:
            fitted = affine_s_from_history(
                np.array(thetas), np.array(phasors), min_spread_rad=0.05 * max(float(np.hypot(*theta)), 1e-4)
            )
            if fitted is not None and abs(np.linalg.det(fitted)) > 1e-30:
                difference = np.linalg.norm(fitted - s_used) / np.linalg.norm(s_used)
                if difference > options.s_refine_tolerance:
                    s_used, s_source = fitted, f"fitted over {len(thetas)} blocks"
                    s_replaced_after = s_replaced_after or blocks
        # a plant whose 2x2 path has a conjugate part (dead time, L_d != L_q) can swell for a few blocks
        # while it spirals in; growth past the uncompensated level is what divergence looks like
        growing = growing + 1 if amp > max(options.divergence_factor * best_amp, uncompensated) else 0
        at_limit = at_limit + 1 if (limited and amp >= best_amp) else 0
        if growing >= options.divergence_blocks or at_limit >= options.divergence_blocks:
            diverged = True
            break
        if blocks - best_block >= options.stall_blocks or session.plant_time_s > options.max_plant_s:
            break
        # at the noise floor: the block cannot resolve further progress
        if amp <= 3.0 * math.sqrt(2.0) * window.noise_std_fs and window.noise_std_fs <= limit / PRECISION_FOR_TARGET:
            break

    details = {
        "blocks": blocks,
        "mu_per_s": options.mu_per_s,
        "block_periods": block_periods,
        "gain_per_block": gain,
        "converged": final is not None,
        "diverged": diverged,
        "s_used": s_source,
        "s_replaced_after_blocks": s_replaced_after,
        "s_hat_phase_offset_deg": options.s_hat_phase_offset_deg,
        "prior": None if prior is None else prior.source,
        "time_to_40db_s": time_to_suppression(history, uncompensated, 40.0),
    }
    if diverged:
        details["divergence"] = (
            "sensor over range after a step"
            if over_range
            else "residual growing"
            if growing >= options.divergence_blocks
            else "theta held at gamma_max"
        )
        session.apply_theta(*best_theta)  # revert to the best theta seen
        if options.fallback:
            probe_opts = ProbeOptions(target_db=options.target_db, max_window_s=options.max_window_s)
            result = identify_probe(
                session,
                s_hat,
                probe_opts,
                gamma_max_rad,
                before=before,
                conditions=conditions,
                start_theta=cast(tuple[float, float], tuple(best_theta)),  # float64 is a float
                history=history,
                method="adaptive",
                details={**details, "fallback": "probe"},
            )
            # the probe continued the same history, so its time_to_40db_s counts from the adaptive start
            result.message = f"adaptation diverged ({details['divergence']}); probe fallback: {result.message}"
            return result
    if final is None:
        session.apply_theta(*best_theta)
        final = session.measure(block_periods, max_noise_std_fs=limit / PRECISION_FOR_TARGET, max_periods=max_periods)
        history.append(_row(final, best_theta))
        theta = best_theta
    else:
        theta = thetas[-1]
    suppression = 20.0 * math.log10(max(uncompensated, 1e-300) / max(final.phasor.amplitude, 1e-300))
    status, message = verdict(suppression, options.target_db, final, uncompensated, conditions, limited)
    if diverged:
        status, message = "failed", f"adaptation diverged ({details['divergence']}); best theta restored: {message}"
    how = f"{blocks} block(s)" + (
        f", S_hat replaced by the fitted S after {s_replaced_after}" if s_replaced_after else ""
    )
    # report the model against what the run measured: the S it switched to, or its own fit
    s_fitted = (
        s_used
        if s_used is not s_model
        else affine_s_from_history(
            np.array(thetas), np.array(phasors), min_spread_rad=0.05 * max(float(np.hypot(*theta)), 1e-4)
        )
    )
    return _result(
        session, status, f"{message} ({how})", theta, before, final, history, s_hat, s_fitted, options, details
    )


def _result(
    session: MeasurementSession,
    status: str,
    message: str,
    theta: np.ndarray,
    before: Window,
    after: Window,
    history: list[list[float]],
    s_hat: complex,
    s_fitted: np.ndarray | None,
    options: AdaptiveOptions,
    details: dict[str, Any],
) -> IdentificationResult:
    s_measured = None if s_fitted is None else rotation_part(s_fitted)
    if s_fitted is not None and s_measured is not None:  # both or neither
        details = {
            **details,
            "s_matrix": s_fitted.tolist(),
            "model_gain_error_db": 20 * math.log10(abs(s_hat) / abs(s_measured)),
            "model_phase_error_deg": phase_error_deg(s_hat, s_measured),
        }
    return IdentificationResult(
        method="adaptive",
        harmonic_order=session.harmonic_order,
        status=status,
        message=message,
        theta_cos=float(theta[0]),
        theta_sin=float(theta[1]),
        residual=after.phasor,
        uncompensated=before.phasor,
        plant_time_s=session.plant_time_s,
        windows_used=len(history),
        windows_discarded=session.windows_discarded,
        s_model=s_hat,
        s_measured=s_measured,
        target_db=options.target_db,
        noise_floor_db=noise_floor_db(after, before.phasor.amplitude),
        details=details,
        traces={"theta_history": history, "theta_history_columns": HISTORY_COLUMNS, **spectrum_traces(before, after)},
    )
