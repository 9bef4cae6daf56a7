"""Grid search (paper sec. 3, Fig. 8) with an affine least-squares fit over all grid points (ours).

Every grid point (gamma_i, delta_i) gives a measured phasor A_i. The plant is affine in theta
(eq. 15: A = S (Theta_d + Theta)), so all points together determine S and B = S Theta_d by complex
linear least squares A_i = S Theta_i + B, and theta* = -Theta_d = -B / S, far finer than the grid step.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.identification.common import measure_uncompensated, spectrum_traces, verify
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementSession
from service.secondary_path import theta_from_gamma_delta, theta_complex, theta_parts


class GridOptions(BaseModel):
    """The paper's grid by default: gamma 0.5..10 deg step 0.5, delta 0..340 deg step 20 (360 points)."""
    model_config = ConfigDict(extra="forbid")
    gamma_start_deg: float = Field(0.5, ge=0, le=45)
    gamma_stop_deg: float = Field(10.0, ge=0, le=45)
    gamma_step_deg: float = Field(0.5, gt=0)
    delta_start_deg: float = Field(0.0, ge=0, lt=360)
    delta_stop_deg: float = Field(340.0, ge=0, lt=360)
    delta_step_deg: float = Field(20.0, gt=0)
    window_periods: int = Field(18, ge=2, le=10_000)
    verify_periods: int = Field(144, ge=2)
    result: str = Field("fit", pattern="^(fit|minimum)$", description="which theta the result reports and verifies")

    @model_validator(mode="after")
    def _ranges(self):
        if self.gamma_stop_deg < self.gamma_start_deg:
            raise ValueError("gamma_stop_deg must be >= gamma_start_deg")
        if self.delta_stop_deg < self.delta_start_deg:
            raise ValueError("delta_stop_deg must be >= delta_start_deg")
        if len(self.gammas_deg()) * len(self.deltas_deg()) > 20_000:
            raise ValueError("grid has more than 20000 points")
        return self

    def gammas_deg(self) -> np.ndarray:
        return np.round(np.arange(self.gamma_start_deg, self.gamma_stop_deg + 1e-9, self.gamma_step_deg), 9)

    def deltas_deg(self) -> np.ndarray:
        return np.round(np.arange(self.delta_start_deg, self.delta_stop_deg + 1e-9, self.delta_step_deg), 9)


def affine_fit(thetas: np.ndarray, phasors: np.ndarray) -> tuple[complex, complex, float]:
    """Least squares A_i = S Theta_i + B over complex arrays; returns (S, Theta*, rms residual)."""
    design = np.column_stack([thetas, np.ones_like(thetas)])
    (s, b), *_ = np.linalg.lstsq(design, phasors, rcond=None)
    rms = float(np.sqrt(np.mean(np.abs(design @ np.array([s, b]) - phasors) ** 2)))
    return complex(s), complex(-b / s), rms


def identify_grid(session: MeasurementSession, s_hat: complex | None, options: GridOptions,
                  gamma_max_rad: float) -> IdentificationResult:
    h = session.harmonic_order
    before = measure_uncompensated(session, options.verify_periods)
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
    s_fit, theta_fit, fit_rms = affine_fit(thetas, phasors)
    if abs(theta_fit) > gamma_max_rad:
        theta_fit = theta_fit * (gamma_max_rad / abs(theta_fit))
    min_tc, min_ts = float(grid[best, 2]), float(grid[best, 3])
    fit_tc, fit_ts = theta_parts(theta_fit)
    tc, ts = (fit_tc, fit_ts) if options.result == "fit" else (min_tc, min_ts)
    after = verify(session, tc, ts, options.verify_periods)
    return IdentificationResult(
        method="grid", harmonic_order=h, status="ok", message=f"{len(points)} grid points",
        theta_cos=tc, theta_sin=ts, residual=after.phasor, uncompensated=before.phasor,
        plant_time_s=session.plant_time_s, windows_used=len(points) + 2,
        windows_discarded=session.windows_discarded, s_model=s_hat, s_measured=s_fit,
        details={
            "points": len(points),
            "minimum": {"gamma_deg": float(grid[best, 0]), "delta_deg": float(grid[best, 1]),
                        "theta_cos": min_tc, "theta_sin": min_ts, "amplitude_fs": float(amplitude[best])},
            "fit": {"theta_cos": fit_tc, "theta_sin": fit_ts,
                    "gamma_deg": math.degrees(abs(theta_fit)),
                    "delta_deg": math.degrees(np.angle(theta_fit)) % 360.0, "rms_fs": fit_rms},
            "reported": options.result,
        },
        traces={"grid": np.round(grid[:, [0, 1, 4, 5]], 7).tolist(),
                "grid_columns": ["gamma_deg", "delta_deg", "a_c", "a_s"],
                **spectrum_traces(before, after)},
    )
