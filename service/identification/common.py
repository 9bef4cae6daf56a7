"""Pieces every method shares: the uncompensated reference, the final verification, trace snippets."""
from __future__ import annotations

import numpy as np

from service.harmonic import amplitude_spectrum
from service.identification.session import MeasurementSession, Window

SPECTRUM_MAX_ORDER = 24
SNIPPET_SAMPLES = 800


def measure_uncompensated(session: MeasurementSession, periods: int) -> Window:
    """The reference: the h-th phasor with theta = 0 (suppression_db is counted against it)."""
    session.apply_theta(0.0, 0.0)
    return session.measure(periods)


def verify(session: MeasurementSession, theta_cos: float, theta_sin: float, periods: int) -> Window:
    """Apply the final theta and measure the residual over a longer window."""
    session.apply_theta(theta_cos, theta_sin)
    return session.measure(periods)


def spectrum_traces(before: Window, after: Window) -> dict:
    """Data for the paper's Fig. 10: alpha over a few periods and its order spectrum, before/after."""
    def snippet(w: Window) -> dict:
        n = min(SNIPPET_SAMPLES, len(w.alpha_fs))
        return {"angle_rad": np.round(np.unwrap(w.angle_rad[:n]), 5).tolist(),
                "alpha_fs": np.round(w.alpha_fs[:n], 6).tolist()}
    return {
        "spectrum_before": amplitude_spectrum(before.alpha_fs, before.angle_rad, SPECTRUM_MAX_ORDER),
        "spectrum_after": amplitude_spectrum(after.alpha_fs, after.angle_rad, SPECTRUM_MAX_ORDER),
        "alpha_before": snippet(before),
        "alpha_after": snippet(after),
    }


def time_to_suppression(history: list, uncompensated_amplitude: float, target_db: float) -> float | None:
    """Plant time (s) at the end of the first window whose residual is `target_db` below the
    uncompensated amplitude; None if none was. history rows: [plant_time_s, theta_cos, theta_sin, amplitude]."""
    limit = uncompensated_amplitude * 10 ** (-target_db / 20.0)
    for t, _tc, _ts, amp in history[1:]:
        if amp <= limit:
            return t
    return None
