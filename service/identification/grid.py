"""Grid search (paper sec. 3, Fig. 8) with an affine least-squares fit over all grid points (ours).

Every grid point (gamma_i, delta_i) gives a measured phasor A_i. The plant is affine in the
injection's h-th harmonic (eq. 15: A = S (Theta_d + Theta)), so all points together determine S and
B = S Theta_d by complex linear least squares A_i = S Theta_i + B, and theta* = -B / S, far finer
than the grid step.

The exact rotation (eq. 3-4) is not linear in gamma: u_q* = u_q cos(v) + u_d sin(v) with
v = gamma cos(x), x = h phi_e + delta, and by the Jacobi-Anger expansion
    sin(gamma cos x) = 2 J1(gamma) cos x - 2 J3(gamma) cos 3x + ...,  cos(gamma cos x) = J0(gamma) - 2 J2(gamma) cos 2x + ...
so the h-th harmonic of the injected voltage is exactly proportional to 2 J1(gamma) e^{j delta}, not to
gamma e^{j delta} (they differ by gamma^2/8: 0.4 % at 10 deg, enough to bias a 360-point fit by more
than the 40 dB target allows). The fit therefore uses Theta_eff = 2 J1(gamma) e^{j delta} and maps the
result back by solving 2 J1(gamma*) = |Theta_eff*|. A second fit over the points near theta* then
removes what other non-linearity (dead time, saturation) leaves.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from scipy import optimize, special

from service.identification.common import (
    PRECISION_FOR_TARGET,
    Conditions,
    MethodOptions,
    Prior,
    measure_reference,
    noise_floor_db,
    periods_for,
    spectrum_traces,
    target_amplitude,
    verdict,
)
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementSession
from service.model.secondary_path import rotation_part, theta_from_gamma_delta, theta_parts

MAX_GRID_POINTS = 2_000  # x about 30 ms of plant time each: about a minute per operating point


def _count(start_deg: float, stop_deg: float, step_deg: float) -> int:
    """Values of start..stop (inclusive) by step, counted without building them (a subnormal step
    makes the ratio infinite: counted as more than any grid may have)."""
    ratio = (stop_deg - start_deg) / step_deg
    return math.floor(ratio + 1e-9) + 1 if ratio < 1e12 else 10**12


class GridOptions(MethodOptions):
    """The paper's grid by default: gamma 0.5..10 deg step 0.5, delta 0..340 deg step 20 (360 points)."""

    gamma_start_deg: float = Field(0.5, ge=0, le=45)
    gamma_stop_deg: float = Field(10.0, ge=0, le=45)
    gamma_step_deg: float = Field(0.5, gt=0, validate_default=True)
    delta_start_deg: float = Field(0.0, ge=0, lt=360)
    delta_stop_deg: float = Field(340.0, ge=0, lt=360)
    delta_step_deg: float = Field(20.0, gt=0, validate_default=True)
    window_periods: int = Field(18, ge=2, le=2_000, description="harmonic periods per grid point")
    settle_s: float = Field(
        0.01,
        ge=0,
        le=2.0,
        description="plant time after each grid point's theta before measuring "
        "(the shaft mode a theta step rings is fitted as a nuisance, not waited out)",
    )
    result: str = Field("fit", pattern="^(fit|minimum)$", description="which theta the result reports and verifies")

    # counted before anything is allocated (a tiny step must not ask numpy for terabytes); field
    # validators, so that a refusal names the step at fault
    @field_validator("gamma_step_deg")
    @classmethod
    def _gamma_count(cls, step: float, info: ValidationInfo) -> float:
        start, stop = info.data.get("gamma_start_deg"), info.data.get("gamma_stop_deg")
        if start is not None and stop is not None:
            if stop < start:
                raise ValueError("gamma_stop_deg must be >= gamma_start_deg")
            if _count(start, stop, step) > MAX_GRID_POINTS:
                raise ValueError(f"{_count(start, stop, step)} gamma values, more than {MAX_GRID_POINTS} grid points")
        return step

    @field_validator("delta_step_deg")
    @classmethod
    def _point_count(cls, step: float, info: ValidationInfo) -> float:
        start, stop = info.data.get("delta_start_deg"), info.data.get("delta_stop_deg")
        if start is None or stop is None:
            return step
        if stop < start:
            raise ValueError("delta_stop_deg must be >= delta_start_deg")
        g: list[Any] = [info.data.get(k) for k in ("gamma_start_deg", "gamma_stop_deg", "gamma_step_deg")]
        n_gamma = _count(*g) if None not in g else 1
        if n_gamma * _count(start, stop, step) > MAX_GRID_POINTS:
            raise ValueError(
                f"the grid has {n_gamma} x {_count(start, stop, step)} points, more than "
                f"{MAX_GRID_POINTS}: choose larger steps"
            )
        return step

    def plant_time_bound_s(self, harmonic_frequency_hz: float) -> float:
        """Worst-case plant time (s): every grid point's settle and window, plus reference and verification."""
        n_points = len(self.gammas_deg()) * len(self.deltas_deg())
        point_s = self.settle_s + 1.05 * self.window_periods / harmonic_frequency_hz
        return n_points * point_s + 2 * (self.max_window_s + self.settle_s)

    def gammas_deg(self) -> np.ndarray:
        return np.round(np.arange(self.gamma_start_deg, self.gamma_stop_deg + 1e-9, self.gamma_step_deg), 9)

    def deltas_deg(self) -> np.ndarray:
        return np.round(np.arange(self.delta_start_deg, self.delta_stop_deg + 1e-9, self.delta_step_deg), 9)


def effective_injection(theta: np.ndarray) -> np.ndarray:
    """Theta_eff = 2 J1(gamma) e^{j delta}: the h-th harmonic the exact rotation injects (see module doc)."""
    gamma = np.abs(theta)
    scale = np.where(gamma > 1e-12, 2.0 * special.j1(gamma) / np.maximum(gamma, 1e-12), 1.0)
    return theta * scale


def gamma_from_effective(gamma_eff: float) -> float:
    """Inverse of gamma -> 2 J1(gamma) on [0, 1.8] rad (monotonic there)."""
    if gamma_eff <= 0.0:
        return 0.0
    if gamma_eff >= 2.0 * special.j1(1.8):
        return 1.8
    return float(optimize.brentq(lambda g: 2.0 * special.j1(g) - gamma_eff, 0.0, 1.8, xtol=1e-12))


def affine_fit(thetas: np.ndarray, phasors: np.ndarray) -> tuple[complex, complex, float, np.ndarray]:
    """Least squares of the general real-affine model a = M theta_eff + b (2x2 real M, the
    S_ss of docs/conventions.md, Secondary path, without assuming its rotation structure: a machine
    with L_d != L_q, dead time or saturation answers cos- and sin-injections differently). Returns (S, theta*, rms, M) where S is
    the rotation part of M, (M11 + M22)/2 + j (M12 - M21)/2, and theta* = -M^-1 b mapped back from
    Theta_eff to gamma."""
    eff = effective_injection(thetas)
    design = np.column_stack([eff.real, -eff.imag, np.ones(len(eff))])  # [theta_cos, theta_sin, 1]
    target = np.column_stack([phasors.real, -phasors.imag])  # [a_c, a_s]
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    m = coef[:2].T  # a = m @ theta + b
    b = coef[2]
    rms = float(np.sqrt(np.mean(np.sum((design @ coef - target) ** 2, axis=1))))
    theta_eff = -np.linalg.solve(m, b)
    theta_eff_c = complex(theta_eff[0], -theta_eff[1])
    theta = np.exp(1j * np.angle(theta_eff_c)) * gamma_from_effective(abs(theta_eff_c))
    return rotation_part(m), complex(theta), rms, m


def local_affine_fit(
    thetas: np.ndarray, phasors: np.ndarray, around: complex, radius_rad: float, min_points: int = 12
) -> tuple[complex, complex, float, int, np.ndarray]:
    """The affine fit over the points within `radius_rad` of `around` (at least the `min_points` nearest)."""
    distance = np.abs(thetas - around)
    near = distance <= radius_rad
    if near.sum() < min_points:
        near = distance <= np.sort(distance)[min(min_points, len(distance)) - 1]
    s, theta, rms, m = affine_fit(thetas[near], phasors[near])
    return s, theta, rms, int(near.sum()), m


def identify_grid(
    session: MeasurementSession,
    s_hat: complex | None,
    options: GridOptions,
    gamma_max_rad: float,
    *,
    prior: Prior | None = None,
    conditions: Conditions | None = None,
) -> IdentificationResult:
    """The paper's grid; `prior` is accepted for a common signature and not used (the grid is a cross-check)."""
    h = session.harmonic_order
    session.settle_after_theta_s = options.settle_s
    max_periods = max(options.window_periods, periods_for(session, options.max_window_s))
    before = measure_reference(session, options.window_periods, max_periods)
    limit = target_amplitude(before.phasor.amplitude, options.target_db)
    points = []
    for gamma_deg in options.gammas_deg():
        if math.radians(gamma_deg) > gamma_max_rad + 1e-12:
            continue  # never send more than gamma_max to the drive
        for delta_deg in options.deltas_deg():
            tc, ts = theta_from_gamma_delta(math.radians(gamma_deg), math.radians(delta_deg))
            session.apply_theta(tc, ts)
            w = session.measure(options.window_periods)
            points.append((gamma_deg, delta_deg, tc, ts, w.phasor.a_c, w.phasor.a_s))
    grid = np.array(points)
    amplitude = np.hypot(grid[:, 4], grid[:, 5])
    best = int(np.argmin(amplitude))
    thetas = grid[:, 2] - 1j * grid[:, 3]
    phasors = grid[:, 4] - 1j * grid[:, 5]
    s_global, theta_global, global_rms, _ = affine_fit(thetas, phasors)
    radius = max(math.radians(3 * options.gamma_step_deg), 0.5 * abs(theta_global))
    s_fit, theta_fit, fit_rms, fit_points, m_fit = local_affine_fit(thetas, phasors, theta_global, radius)
    if abs(theta_fit) > gamma_max_rad:
        theta_fit = theta_fit * (gamma_max_rad / abs(theta_fit))
    min_tc, min_ts = float(grid[best, 2]), float(grid[best, 3])
    fit_tc, fit_ts = theta_parts(theta_fit)
    tc, ts = (fit_tc, fit_ts) if options.result == "fit" else (min_tc, min_ts)
    session.apply_theta(tc, ts)
    after = session.measure(
        options.window_periods, max_noise_std_fs=limit / PRECISION_FOR_TARGET, max_periods=max_periods
    )
    suppression = 20.0 * math.log10(max(before.phasor.amplitude, 1e-300) / max(after.phasor.amplitude, 1e-300))
    status, message = verdict(suppression, options.target_db, after, before.phasor.amplitude, conditions, False)
    return IdentificationResult(
        method="grid",
        harmonic_order=h,
        status=status,
        message=f"{message} ({len(points)} grid points, {options.result})",
        target_db=options.target_db,
        noise_floor_db=noise_floor_db(after, before.phasor.amplitude),
        theta_cos=tc,
        theta_sin=ts,
        residual=after.phasor,
        uncompensated=before.phasor,
        plant_time_s=session.plant_time_s,
        windows_used=len(points) + 2,
        windows_discarded=session.windows_discarded,
        s_model=s_hat,
        s_measured=s_fit,
        details={
            "points": len(points),
            "minimum": {
                "gamma_deg": float(grid[best, 0]),
                "delta_deg": float(grid[best, 1]),
                "theta_cos": min_tc,
                "theta_sin": min_ts,
                "amplitude_fs": float(amplitude[best]),
            },
            "fit": {
                "theta_cos": fit_tc,
                "theta_sin": fit_ts,
                "gamma_deg": math.degrees(abs(theta_fit)),
                "delta_deg": math.degrees(np.angle(theta_fit)) % 360.0,
                "rms_fs": fit_rms,
                "points": fit_points,
                "radius_deg": math.degrees(radius),
                "s_matrix": m_fit.tolist(),
            },
            "fit_global": {
                "gamma_deg": math.degrees(abs(theta_global)),
                "delta_deg": math.degrees(np.angle(theta_global)) % 360.0,
                "rms_fs": global_rms,
                "s": {"re": s_global.real, "im": s_global.imag},
            },
            "reported": options.result,
        },
        traces={
            "grid": np.round(grid[:, [0, 1, 4, 5]], 7).tolist(),
            "grid_columns": ["gamma_deg", "delta_deg", "a_c", "a_s"],
            **spectrum_traces(before, after),
        },
    )
