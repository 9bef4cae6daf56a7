"""Adaptive identification (paper sec. 2.3) in the block form of DESIGN section 3.

Continuous law (eq. 16): d(theta)/dt = -2 mu S_hat^+ x(t) alpha(t). Averaged over whole periods of
the harmonic, x(t) alpha(t) averages to a/2 with a = [a_c, a_s], so over one block of length
T_block the update is

    theta <- theta - mu * T_block * S_hat^+ a                                  (DESIGN 3)

In complex form (secondary_path): Theta <- Theta - g * A / S_hat with g = mu*T_block. With
S_hat = S this is a contraction by (1 - g) per block; with a phase error phi it is
|1 - g*(|S|/|S_hat|)*exp(j phi)|, which is < 1 for small g iff |phi| < 90 deg.

Limits (sec. 2.4): |theta| <= gamma_max with the state itself clamped (anti-windup); adaptation is
held off where the model says the injection lacks the authority to cancel the harmonic (the gamma
it needs, |A_0 / S_hat|, is more than 1.5 gamma_max; a weak secondary path shows up there too).
Stopping: converged when theta has settled and the residual no longer falls; diverged when the
residual grows well above the best seen or theta runs into gamma_max without the residual
falling -- then the best theta seen is restored and the probe method takes over from there.
"""
from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from service.harmonic import electrical_frequency_hz
from service.identification.common import measure_uncompensated, spectrum_traces, time_to_suppression, verify
from service.identification.probe import ProbeOptions, identify_probe
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementSession
from service.secondary_path import theta_parts


class AdaptiveOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mu_per_s: float = Field(12.5, gt=0, description="adaptation gain mu of eq. 16, 1/s")
    block_periods: int = Field(36, ge=2, le=10_000, description="harmonic periods per adaptation block")
    settle_s: float = Field(0.02, ge=0, le=10, description="plant time after each theta update before its block is measured")
    max_blocks: int = Field(80, ge=1, le=10_000)
    theta_tolerance_deg: float = Field(0.005, gt=0, description="|delta theta| below which a block counts as settled")
    settled_blocks: int = Field(2, ge=1, description="consecutive settled blocks that end the adaptation")
    divergence_factor: float = Field(2.0, gt=1, description="residual above this times the best seen counts as growing")
    divergence_blocks: int = Field(3, ge=1, description="consecutive growing blocks that mean divergence")
    fallback: bool = Field(True, description="on divergence, fall back to the probe method")
    verify_periods: int = Field(144, ge=2, description="periods of the final residual measurement")
    reference_periods: int = Field(72, ge=2, description="periods of the uncompensated reference measurement")
    gamma_max_deg: float | None = Field(None, gt=0, le=45, description="defaults to the settings' gamma_max")
    s_hat_phase_offset_deg: float = Field(0.0, ge=-180, le=180,
                                          description="deliberate phase error added to S_hat (robustness tests)")


def clamp_gamma(theta: complex, gamma_max_rad: float) -> tuple[complex, bool]:
    """Scale Theta back onto |Theta| = gamma_max (anti-windup of sec. 2.4)."""
    if abs(theta) > gamma_max_rad:
        return theta * (gamma_max_rad / abs(theta)), True
    return theta, False


def identify_adaptive(session: MeasurementSession, s_hat: complex, options: AdaptiveOptions,
                      gamma_max_rad: float) -> IdentificationResult:
    h = session.harmonic_order
    session.settle_after_theta_s = options.settle_s
    s_used = s_hat * complex(math.cos(math.radians(options.s_hat_phase_offset_deg)),
                             math.sin(math.radians(options.s_hat_phase_offset_deg)))
    before = measure_uncompensated(session, options.reference_periods)
    history = [[before.end_time_s, 0.0, 0.0, before.phasor.amplitude]]

    needed_gamma = abs(before.phasor.complex / s_hat)
    if needed_gamma > 1.5 * gamma_max_rad:
        # sec. 2.4: hold the adaptation off; nothing above 0 is sent
        return _result(session, "no_authority", f"model needs gamma = {math.degrees(needed_gamma):.1f} deg > "
                       f"gamma_max = {math.degrees(gamma_max_rad):.1f} deg: adaptation held off (sec. 2.4)",
                       0j, before, before, history, s_hat, {"blocks": 0, "needed_gamma_deg": math.degrees(needed_gamma)})

    theta = 0j
    best_theta, best_amp = 0j, before.phasor.amplitude
    window = before
    settled = growing = at_limit = 0
    limited = diverged = False
    blocks = 0
    for blocks in range(1, options.max_blocks + 1):
        block_s = options.block_periods / (h * abs(electrical_frequency_hz(window.angle_rad, session.sample_rate_hz)))
        step = options.mu_per_s * block_s * window.phasor.complex / s_used       # eq. 16, block form
        new_theta, limited = clamp_gamma(theta - step, gamma_max_rad)
        change = abs(new_theta - theta)
        theta = new_theta
        session.apply_theta(*theta_parts(theta))
        window = session.measure(options.block_periods)
        amp = window.phasor.amplitude
        history.append([window.end_time_s, *theta_parts(theta), amp])
        if amp < best_amp:
            best_theta, best_amp = theta, amp
        # a plant whose 2x2 path has a conjugate part (dead time, L_d != L_q) can swell for a few blocks
        # while it spirals in; growth past the uncompensated level is what divergence looks like
        growing = growing + 1 if amp > max(options.divergence_factor * best_amp, before.phasor.amplitude) else 0
        at_limit = at_limit + 1 if (limited and amp >= best_amp) else 0
        if growing >= options.divergence_blocks or at_limit >= options.divergence_blocks:
            diverged = True
            break
        falling = len(history) >= 3 and amp < 0.9 * history[-2][3]
        settled = settled + 1 if (change < math.radians(options.theta_tolerance_deg) and not falling) else 0
        if settled >= options.settled_blocks:
            break

    details = {"blocks": blocks, "mu_per_s": options.mu_per_s, "block_periods": options.block_periods,
               "converged": settled >= options.settled_blocks, "diverged": diverged,
               "s_hat_phase_offset_deg": options.s_hat_phase_offset_deg,
               "time_to_40db_s": time_to_suppression(history, before.phasor.amplitude, 40.0)}
    if diverged:
        details["divergence"] = "residual growing" if growing >= options.divergence_blocks else "theta held at gamma_max"
        session.apply_theta(*theta_parts(best_theta))      # revert to the best theta seen
        if options.fallback:
            probe_opts = ProbeOptions(verify_periods=options.verify_periods)
            result = identify_probe(session, s_hat, probe_opts, gamma_max_rad, before=before,
                                    start_theta=theta_parts(best_theta), history=history, method="adaptive",
                                    details={**details, "fallback": "probe"})
            # the probe continued the same history, so its time_to_40db_s counts from the adaptive start
            result.message = f"adaptation diverged ({details['divergence']}); probe fallback: {result.message}"
            return result
        after = verify(session, *theta_parts(best_theta), options.verify_periods)
        return _result(session, "failed", "adaptation diverged; best theta restored", best_theta, before, after,
                       history, s_hat, details)

    after = verify(session, *theta_parts(theta), options.verify_periods)
    status = "ok"
    message = f"converged after {blocks} blocks" if details["converged"] else f"stopped after {blocks} blocks without settling"
    if limited and after.phasor.amplitude > 0.1 * before.phasor.amplitude:
        status, message = "no_authority", "gamma_max reached: the injection cannot cancel the harmonic here (sec. 2.4)"
    return _result(session, status, message, theta, before, after, history, s_hat, details)


def _result(session, status, message, theta, before, after, history, s_hat, details) -> IdentificationResult:
    tc, ts = theta_parts(theta)
    return IdentificationResult(
        method="adaptive", harmonic_order=session.harmonic_order, status=status, message=message,
        theta_cos=tc, theta_sin=ts, residual=after.phasor, uncompensated=before.phasor,
        plant_time_s=session.plant_time_s, windows_used=len(history) + 1,
        windows_discarded=session.windows_discarded, s_model=s_hat, details=details,
        traces={"theta_history": history, "theta_history_columns": ["plant_time_s", "theta_cos", "theta_sin", "amplitude_fs"],
                **spectrum_traces(before, after)},
    )
