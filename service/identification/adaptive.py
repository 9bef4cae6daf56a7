"""Adaptive identification (paper sec. 2.3) in the block form of DESIGN section 3.

Continuous law (eq. 16): d(theta)/dt = -2 mu S_hat^+ x(t) alpha(t). Averaged over whole periods of
the harmonic, x(t) alpha(t) averages to a/2 with a = [a_c, a_s], so over one block of length
T_block the update is

    theta <- theta - mu * T_block * S_hat^+ a                                  (DESIGN 3)

In complex form (secondary_path): Theta <- Theta - g * A / S_hat with g = mu*T_block. With
S_hat = S this is a contraction by (1 - g) per block; with a phase error phi it is
|1 - g*(|S|/|S_hat|)*exp(j phi)|, which is < 1 for small g iff |phi| < 90 deg.
Limits (sec. 2.4): |theta| <= gamma_max, and the state itself is clamped (anti-windup).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from service.harmonic import electrical_frequency_hz
from service.identification.common import measure_uncompensated, spectrum_traces, verify
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementSession
from service.secondary_path import theta_complex, theta_parts


class AdaptiveOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mu_per_s: float = Field(12.5, gt=0, description="adaptation gain mu of eq. 16, 1/s")
    block_periods: int = Field(36, ge=2, le=10_000, description="harmonic periods per adaptation block")
    max_blocks: int = Field(60, ge=1, le=10_000)
    theta_tolerance_deg: float = Field(0.005, gt=0, description="|delta theta| below which a block counts as settled")
    settled_blocks: int = Field(2, ge=1, description="consecutive settled blocks that end the adaptation")
    verify_periods: int = Field(144, ge=2, description="periods of the final residual measurement")
    gamma_max_deg: float | None = Field(None, gt=0, le=45, description="defaults to the settings' gamma_max")


def clamp_gamma(theta: complex, gamma_max_rad: float) -> tuple[complex, bool]:
    """Scale Theta back onto |Theta| = gamma_max (anti-windup of sec. 2.4)."""
    if abs(theta) > gamma_max_rad:
        return theta * (gamma_max_rad / abs(theta)), True
    return theta, False


def identify_adaptive(session: MeasurementSession, s_hat: complex, options: AdaptiveOptions,
                      gamma_max_rad: float) -> IdentificationResult:
    h = session.harmonic_order
    before = measure_uncompensated(session, options.verify_periods)
    theta = 0j
    history = [[before.end_time_s, 0.0, 0.0, before.phasor.amplitude]]
    settled = 0
    window = before
    limited = False
    blocks = 0
    for blocks in range(1, options.max_blocks + 1):
        block_s = options.block_periods / (h * abs(electrical_frequency_hz(window.angle_rad, session.sample_rate_hz)))
        gain = options.mu_per_s * block_s
        step = gain * window.phasor.complex / s_hat
        new_theta, limited = clamp_gamma(theta - step, gamma_max_rad)
        change = abs(new_theta - theta)
        theta = new_theta
        session.apply_theta(*theta_parts(theta))
        window = session.measure(options.block_periods)
        tc, ts = theta_parts(theta)
        history.append([window.end_time_s, tc, ts, window.phasor.amplitude])
        settled = settled + 1 if change < math.radians(options.theta_tolerance_deg) else 0
        if settled >= options.settled_blocks:
            break
    after = verify(session, *theta_parts(theta), options.verify_periods)
    tc, ts = theta_parts(theta)
    status, message = "ok", f"converged after {blocks} blocks" if settled >= options.settled_blocks else f"stopped after {blocks} blocks without settling"
    if limited:
        status, message = "no_authority", "gamma_max reached: the injection cannot cancel the harmonic here (sec. 2.4)"
    return IdentificationResult(
        method="adaptive", harmonic_order=h, status=status, message=message,
        theta_cos=tc, theta_sin=ts, residual=after.phasor, uncompensated=before.phasor,
        plant_time_s=session.plant_time_s, windows_used=blocks + 2,
        windows_discarded=session.windows_discarded, s_model=s_hat,
        details={"blocks": blocks, "mu_per_s": options.mu_per_s, "block_periods": options.block_periods,
                 "converged": settled >= options.settled_blocks},
        traces={"theta_history": history, "theta_history_columns": ["plant_time_s", "theta_cos", "theta_sin", "amplitude_fs"],
                **spectrum_traces(before, after)},
    )

